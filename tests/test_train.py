"""iris-train: the loop runs, logs, checkpoints, resumes exactly, and runs under torchrun (DDP/gloo)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from iris_train import load_model, read_checkpoint  # noqa: E402
from iris_train.model import build_model  # noqa: E402
from iris_train.config import TrainConfig  # noqa: E402
from iris_train.losses import PhotometricLoss  # noqa: E402
from iris_train.batches import draw_batch  # noqa: E402
from iris_train.train import lr_factor, train  # noqa: E402
from iris_train.config import preset  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


@dataclass
class FakeScene:
    images: np.ndarray


def fake_scenes(n=3, seed=0):
    rng = np.random.default_rng(seed)
    return [FakeScene(rng.integers(0, 256, (8, 64, 64, 3), dtype=np.uint8)) for _ in range(n)]


SMALL = dict(scenes_per_step=1, rays_per_scene=32, views_min=3, views_max=4, warmup=2, teacher_weight=0.0,
             teacher_translation_weight=0.0, teacher_focal_weight=0.0,
             log_every=1, ckpt_every=2)


def test_lr_schedule_warms_up_then_decays():
    cfg = TrainConfig(steps=100, warmup=10, lr=1.0, min_lr_ratio=0.1)
    f = [lr_factor(s, cfg) for s in range(100)]
    assert f[0] == pytest.approx(0.1) and f[9] == pytest.approx(1.0)
    assert all(a >= b for a, b in zip(f[10:], f[11:]))         # monotone decay after warm-up
    assert f[-1] == pytest.approx(0.1, abs=1e-3)


def test_draw_batch_splits_views_into_disjoint_reference_and_target_sets():
    cfg = TrainConfig(**SMALL)
    images, ref, tgt, pixels, depths, teacher, pose_batch, solved, colour = draw_batch(
        fake_scenes(), cfg, preset("tiny"), np.random.default_rng(0))
    assert teacher is None and pose_batch is None and solved is None and colour is None
    assert images.dtype == torch.float32 and 0 <= float(images.min()) and float(images.max()) <= 1
    for r, t, p, d in zip(ref, tgt, pixels, depths):
        assert len(r) >= 1 and len(t) >= 1 and not set(r.tolist()) & set(t.tolist())
        assert len(r) + len(t) == images.shape[1]
        assert d.shape == (p.numel(), 64)
        assert bool(((d >= 0.1) & (d <= 1.0)).all())


def test_draw_batch_at_a_colour_size_shrinks_the_encoders_images_from_it():
    """``colour_size``: the rendered scenes' views come from the larger set, the model's images
    are their INTER_AREA copies (as the runtime brings a photo to the model), target pixels
    index the larger grid, and a step trains on them."""
    import cv2
    cfg = TrainConfig(colour_size=256, **SMALL)
    rng = np.random.default_rng(3)
    large = [FakeScene(rng.integers(0, 256, (8, 256, 256, 3), dtype=np.uint8)) for _ in range(2)]
    small = [FakeScene(np.zeros((8, 64, 64, 3), np.uint8)) for _ in range(2)]
    images, ref, tgt, pixels, depths, _, _, _, colour = draw_batch(
        small, cfg, preset("tiny-rgb"), np.random.default_rng(0), colour_scenes=large)
    assert colour.shape[-2:] == (256, 256) and images.shape[-2:] == (64, 64)
    for b in range(images.shape[0]):
        for v in range(images.shape[1]):
            big = (colour[b, v].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
            want = cv2.resize(big, (64, 64), interpolation=cv2.INTER_AREA)
            got = (images[b, v].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
            np.testing.assert_array_equal(got, want)
    assert all(int(p.max()) < 256 * 256 for p in pixels) and any(int(p.max()) >= 64 * 64
                                                                   for p in pixels)
    model = build_model(preset("tiny-rgb"))
    loss, terms = PhotometricLoss(model, cfg)(images, ref, tgt, pixels, depths,
                                              colour_images=colour)
    assert torch.isfinite(loss) and terms["render"] > 0


def test_train_logs_checkpoints_and_resumes_exactly(tmp_path):
    scenes = fake_scenes()
    cfg = TrainConfig(steps=4, **SMALL)
    # Run A: 4 steps straight. Run B: 2 steps, stop, resume for the last 2.
    train(cfg, tmp_path / "a", scenes=scenes, threads=1)
    train(TrainConfig(steps=4, **SMALL), tmp_path / "b", scenes=scenes, threads=1, max_seconds=0.0)
    assert read_checkpoint(tmp_path / "b" / "last.pt")["step"] == 1   # stopped after one step
    train(cfg, tmp_path / "b", scenes=scenes, threads=1, resume=True)
    log = [json.loads(line) for line in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [0, 1, 2, 3]
    assert {"step", "loss", "psnr", "lr", "time"} <= set(log[0])
    a = read_checkpoint(tmp_path / "a" / "last.pt")
    b = read_checkpoint(tmp_path / "b" / "last.pt")
    assert a["step"] == b["step"] == 4 and a["config"] == b["config"]
    model = load_model(tmp_path / "a" / "last.pt")
    assert not model.training
    # The resumed run is the same run: same batches (one generator per step), same optimiser state.
    for k in a["model"]:
        torch.testing.assert_close(a["model"][k], b["model"][k], rtol=0, atol=1e-6, msg=k)
    # ... and training did something.
    torch.manual_seed(cfg.seed)
    from iris_train import build_model
    fresh = build_model(preset("tiny")).state_dict()
    assert any(not torch.equal(fresh[k], a["model"][k]) for k in fresh)


def test_torchrun_two_processes(tmp_path):
    """DistributedDataParallel with gloo on CPU: two processes run the same loop."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--master_port=29517",
           "-m", "iris_train.train", "--out", str(tmp_path / "ddp"), "--steps", "2",
           "--train-scenes", "2", "--scenes-per-step", "1", "--rays-per-scene", "16",
           "--views-min", "3", "--views-max", "3", "--warmup", "1", "--log-every", "1", "--threads", "1"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    log = [json.loads(x) for x in (tmp_path / "ddp" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [0, 1]
    assert read_checkpoint(tmp_path / "ddp" / "last.pt")["step"] == 2


# -- training on the solved cameras (render_cameras="solve") -------------------------------------
def _poses(rng, n):
    from scipy.spatial.transform import Rotation
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3))
    return T


def test_solved_cameras_rebase_to_the_drawn_first_view():
    from iris_train.pseudo_poses import SolvedCameras
    rng = np.random.default_rng(3)
    T = _poses(rng, 8)
    sc = SolvedCameras(T, 1.1, np.ones(8, dtype=bool))
    order = np.array([5, 2, 7])
    out = sc.rebased(order)
    np.testing.assert_allclose(out[0], np.eye(4), atol=1e-12)
    for a in range(3):           # every relative pose is the scene's (float64 reference)
        for b in range(3):
            np.testing.assert_allclose(np.linalg.inv(out[b]) @ out[a],
                                       np.linalg.inv(T[order[b]]) @ T[order[a]], atol=1e-10)


def test_solve_losses_vanish_at_the_solve_and_pull_towards_it():
    from iris_train.losses import solve_losses
    T = torch.as_tensor(_poses(np.random.default_rng(4), 5))
    T[0] = torch.eye(4, dtype=T.dtype)
    f = torch.tensor([0.9, 0.9], dtype=torch.float64)
    at = solve_losses(T, f, T, f)
    assert all(float(v) < 1e-12 for v in at.values())
    pred = T.clone()
    pred[2, :3, 3] += torch.tensor([0.3, 0.0, 0.0], dtype=T.dtype)
    pred.requires_grad_(True)
    out = solve_losses(pred, f * 1.2, T, f)
    assert float(out["solve_trans"].detach()) == pytest.approx(0.3 ** 2 / 4)   # mean over views 1..4
    assert float(out["solve_focal"].detach()) == pytest.approx(np.log(1.2) ** 2)
    out["solve_trans"].backward()
    assert float(pred.grad[2, 0, 3]) > 0 and float(pred.grad[[1, 3, 4]].abs().sum()) == 0


def test_draw_batch_with_solutions_draws_only_solved_views():
    from iris_train.pseudo_poses import SolvedCameras
    rng = np.random.default_rng(5)
    # View v of every scene is the constant image 20 * v, so a drawn image names its view.
    scenes = [FakeScene(np.repeat(20 * np.arange(8, dtype=np.uint8), 64 * 64 * 3).reshape(8, 64, 64, 3))
              for _ in range(3)]
    T = _poses(rng, 8)
    solved = np.array([1, 1, 0, 1, 1, 1, 0, 1], dtype=bool)     # 6 views solved
    sc = SolvedCameras(np.where(solved[:, None, None], T, np.nan), 1.2, solved)
    cfg = TrainConfig(**{**SMALL, "views_min": 5, "views_max": 6, "scenes_per_step": 2})
    for seed in range(5):
        images, _, _, _, _, _, _, cams, _ = draw_batch(scenes, cfg, preset("tiny"),
                                                    np.random.default_rng(seed), solutions=lambda i: sc)
        for b, (world_from_cam, focal) in enumerate(cams):
            views = (images[b, :, 0, 0, 0] * 255 / 20).round().long().numpy()
            assert solved[views].all() and len(set(views)) == len(views)
            np.testing.assert_allclose(world_from_cam.numpy(), sc.rebased(views), atol=1e-5)
            assert focal.tolist() == pytest.approx([1.2, 1.2])
    # No scene has enough solved views: a clear error, not a silent draw of unsolved views.
    cfg7 = TrainConfig(**{**SMALL, "views_min": 7, "views_max": 7})
    with pytest.raises(RuntimeError, match="solved views"):
        draw_batch(scenes, cfg7, preset("tiny"), np.random.default_rng(0), solutions=lambda i: sc)


def test_train_on_solved_cameras_from_an_init_checkpoint(tmp_path):
    """A fine-tune: --init weights, the renderer on the solved cameras of a rendered scene, the
    head distilled on them; a config mismatch is refused."""
    pytest.importorskip("pyrender")
    from iris_train.synthetic import render_scene
    scenes = [render_scene(1_000_003, n_views=8, size=(64, 64))]
    base = dict(SMALL, views_min=4, views_max=4, preset="tiny-rgb")
    train(TrainConfig(steps=1, **base), tmp_path / "init", scenes=scenes, threads=1)
    cfg = TrainConfig(steps=2, render_cameras="solve", solve_rotation_weight=10.0,
                      solve_translation_weight=10.0, solve_focal_weight=1.0, **base)
    train(cfg, tmp_path / "ft", scenes=scenes, threads=1, init=tmp_path / "init" / "last.pt")
    log = [json.loads(x) for x in (tmp_path / "ft" / "log.jsonl").read_text().splitlines()]
    assert {"render", "solve_rot", "solve_trans", "solve_focal"} <= set(log[0]["terms"])
    assert all(np.isfinite(v) for r in log for v in r["terms"].values())
    assert read_checkpoint(tmp_path / "ft" / "last.pt")["step"] == 2
    with pytest.raises(ValueError, match="init"):
        train(TrainConfig(steps=1, **dict(base, preset="tiny")), tmp_path / "bad", scenes=scenes,
              threads=1, init=tmp_path / "init" / "last.pt")
    with pytest.raises(ValueError, match="render_cameras"):
        train(TrainConfig(steps=1, render_cameras="truth", **base), tmp_path / "bad2", scenes=scenes,
              threads=1)


def test_scene_sets_index_through_their_parts():
    from iris_train.scene_sets import SceneSets, per_scene
    a, b = ["a0", "a1"], ["b0", "b1", "b2"]
    sets = SceneSets([a, [], b])
    assert len(sets) == 5
    assert [sets[i] for i in range(5)] == ["a0", "a1", "b0", "b1", "b2"]
    assert sets.part_of(3) == (b, 1)
    with pytest.raises(IndexError):
        sets.part_of(5)

    class Cached(list):            # stands in for a SyntheticScenes: keyed by (cache_dir, seed)
        cache_dir, seeds = "dir", (10, 11)

    class Plain(list):
        pass

    class Data:
        def __init__(self, name):
            self.images = name

    seen = []
    lookup = per_scene(SceneSets([Cached(["c0", "c1"]), Plain([Data("p0")])]),
                        lambda part, i: seen.append(("cached", part.seeds[i])) or part.seeds[i],
                        lambda images: seen.append(("computed", images)) or images)
    assert [lookup(i) for i in (1, 2, 1)] == [11, "p0", 11]
    assert seen == [("cached", 11), ("computed", "p0")]          # memoised


def test_capture_kinds_keep_the_seeds_of_those_kinds_and_refuse_unknown_names():
    from iris_train.scene_sets import capture_seeds
    from iris_train.synthetic import CAPTURE_KINDS, capture_kind
    every = capture_seeds(TrainConfig(capture_scenes=40))
    assert every == list(range(40))
    walks = capture_seeds(TrainConfig(capture_scenes=40, capture_kinds="walk, orbit"))
    assert walks == [s for s in range(40) if capture_kind(s) in ("walk", "orbit")]
    assert 0 < len(walks) < 40
    with pytest.raises(ValueError, match="capture_kinds.*'stroll'"):
        capture_seeds(TrainConfig(capture_scenes=40, capture_kinds="walk,stroll"))
    assert set(CAPTURE_KINDS) >= {"walk", "orbit"}


def test_distortion_loss_against_its_closed_form():
    """One point of weight: only the self term (interval / 3). Two halves at distance d: the
    pair term 2 * 1/4 * d plus the self terms. A ray spread evenly costs more than one point."""
    from iris_train.losses import distortion
    S = 8
    s = (torch.arange(S, dtype=torch.float64) + 0.5) / S
    one = torch.zeros(1, S, dtype=torch.float64)
    one[0, 3] = 1.0
    assert float(distortion(one, s[None], 1 / S)) == pytest.approx(1 / S / 3, rel=1e-12)
    two = torch.zeros(1, S, dtype=torch.float64)
    two[0, 1] = two[0, 6] = 0.5
    d = float(s[6] - s[1])
    assert float(distortion(two, s[None], 1 / S)) == pytest.approx(0.5 * d + 0.5 / S / 3, rel=1e-12)
    flat = torch.full((1, S), 1.0 / S, dtype=torch.float64)
    assert float(distortion(flat, s[None], 1 / S)) > float(distortion(one, s[None], 1 / S))

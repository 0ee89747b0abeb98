"""iris_train.evaluate: the protocol pieces, evaluate() on a random tiny model and on an oracle
runtime, the baselines on hand-made cameras, and the CLI."""
from __future__ import annotations

import dataclasses
import functools
import itertools
import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from iris_train import build_model, preset, save_checkpoint  # noqa: E402
from iris_train.evaluate import (ORDERS, TARGET_FRAMES, evaluate, format_table, main,  # noqa: E402
                                 nearest_reference, presentation_order, rand_permutation,
                                 split_frames, write_json)
from iris_train.metrics import rpa  # noqa: E402

from .tolerances import EPS32, encoder_tol, f32_tol  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SIZE = (16, 16)          # smallest size of the tiny preset's 8-px patches that SSIM (11 taps) takes
RPA_KEYS = ("rpa@5", "rpa@15", "rpa@30")
LOCATE_KEYS = ("locate_rpa@5", "locate_rpa@15", "locate_rpa@30")
REFERENCE_KEYS = ("reference_rpa@5", "reference_rpa@15", "reference_rpa@30")
HEAD_KEYS = ("head_reference_rpa@5", "head_reference_rpa@15", "head_reference_rpa@30")
YAWS = (0.0, 2.0, 4.0, 8.0, 12.0, 20.0, 31.0, 45.0)    # no pair differs by exactly 5, 15 or 30 deg


def rot_y(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def pose(R=np.eye(3), c=(0.0, 0.0, 0.0)):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c
    return T


def rotation_scene(seed=0, centre=(0.3, -0.2, 1.0)):
    """8 random images whose cameras only turn (yaw YAWS) about one centre."""
    rng = np.random.default_rng(seed)
    return SimpleNamespace(images=rng.integers(0, 256, (8, *SIZE, 3), dtype=np.uint8),
                           world_from_cam=np.stack([pose(rot_y(a), centre) for a in YAWS]))


def identity_rpa_of_rotation_scene():
    errs = [abs(a - b) for a, b in itertools.combinations(YAWS, 2)]
    return {f"rpa@{t}": float(np.mean(np.array(errs) < t)) for t in (5, 15, 30)}


@functools.lru_cache(maxsize=1)
def synthetic_or_fake_scene():
    """A held-out synthetic scene if the renderer works here, else random images on an arc."""
    try:
        from iris_train.data import HELDOUT_SEEDS
        from iris_train.synthetic import render_scene
        return render_scene(HELDOUT_SEEDS[0], n_views=8, size=SIZE)
    except Exception:     # no EGL/pyrender: same interface, made up
        rng = np.random.default_rng(5)
        poses = [pose(rot_y(-a), (0.6 * np.sin(np.radians(a)), 0.0, -0.6 * np.cos(np.radians(a))))
                 for a in np.linspace(0, 40, 8)]
        return SimpleNamespace(images=rng.integers(0, 256, (8, *SIZE, 3), dtype=np.uint8),
                               world_from_cam=np.stack(poses))


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    # On a shared 2-core machine two intra-op threads were measured ~25x slower than one.
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def tiny_model():
    torch.manual_seed(0)
    # The tiny preset's widths at 16x16 and 8 samples per ray: the test is about plumbing, and the
    # CPU is shared.
    cfg = dataclasses.replace(preset("tiny"), image_height=SIZE[0], image_width=SIZE[1], samples=8)
    return build_model(cfg).eval()


def check_structure(results):
    """The summary keys (the best-reference baseline and the per-scene records were added)."""
    assert set(results) == {"seq", "rand"}
    for R in results.values():
        assert set(R) == {"model", "baselines", "scenes"}
        assert set(R["model"]) == {"psnr", "ssim", *RPA_KEYS, *LOCATE_KEYS, "depth_spearman",
                                   *REFERENCE_KEYS, *HEAD_KEYS}
        assert set(R["baselines"]) == {"nearest_reference", "mean_colour", "identity_poses",
                                       "best_reference"}
        assert set(R["baselines"]["nearest_reference"]) == {"psnr", "ssim"}
        assert set(R["baselines"]["best_reference"]) == {"psnr", "ssim"}
        assert set(R["baselines"]["mean_colour"]) == {"psnr", "ssim"}
        assert set(R["baselines"]["identity_poses"]) == {*RPA_KEYS, *LOCATE_KEYS}
        for s in R["scenes"]:
            assert set(s) == {"index", "name", "model", "baselines", "cameras"}
            assert set(s["model"]) == set(R["model"])
            assert set(s["baselines"]) == set(R["baselines"])
            assert set(s["cameras"]) == {"source", "references", "references_solved", "targets",
                                         "targets_located", "fallbacks", "scale", "scale_source",
                                         "principal_offset"}


# ----------------------------------------------------------------------------------------------
# Protocol pieces
# ----------------------------------------------------------------------------------------------

def test_split_frames():
    assert split_frames(8) == ((0, 2, 3, 5, 7), TARGET_FRAMES) == ((0, 2, 3, 5, 7), (1, 4, 6))
    for n in range(2, 20):
        refs, targets = split_frames(n)
        assert 0 in refs and targets and sorted(refs + targets) == list(range(n))
    with pytest.raises(ValueError):
        split_frames(1)


def test_rand_permutation_is_fixed_per_scene():
    p = rand_permutation(8, 3)
    assert sorted(p) == list(range(8))
    np.testing.assert_array_equal(p, rand_permutation(8, 3))
    assert any((rand_permutation(8, k) != p).any() for k in range(4, 8))


def test_nearest_reference_on_hand_made_cameras():
    # Pure rotations: the angle decides; a tie goes to the earlier reference.
    rotations = np.stack([pose(rot_y(a)) for a in YAWS])
    assert nearest_reference(rotations, (0, 2, 3, 5, 7), (1, 4, 6)) == [0, 3, 5]
    # Same orientation, cameras on a line: the centre distance decides, whatever the scale.
    xs = (0.0, 1.0, 1.9, 3.0, 4.0, 4.2, 7.0, 9.0)
    for s in (1e-3, 1.0, 50.0):
        line = np.stack([pose(c=(s * x, 0.0, 0.0)) for x in xs])
        assert nearest_reference(line, (0, 2, 3, 5, 7), (1, 4, 6)) == [2, 5, 7]
    # One radian of turning weighs as much as the mean distance from the centroid.
    mixed = np.stack([pose(c=(-1.0, 0, 0)), pose(c=(1.0, 0, 0)), pose(rot_y(np.degrees(0.9)))])
    # spread = 2/3: cost(0 -> 1) = 0 + 2 / (2/3) = 3; cost(0 -> 2) = 0.9 + 1 / (2/3) = 2.4
    assert nearest_reference(mixed, (1, 2), (0,)) == [2]
    assert nearest_reference(mixed, (0, 1), (2,)) == [0]      # a tie


def test_identity_baseline_rpa_on_hand_made_cameras():
    scene = rotation_scene()
    identity = np.broadcast_to(np.eye(4), (8, 4, 4))
    assert rpa(identity, scene.world_from_cam) == identity_rpa_of_rotation_scene()


# ----------------------------------------------------------------------------------------------
# evaluate() with an oracle runtime: checks the plumbing of orders, splits and poses exactly
# ----------------------------------------------------------------------------------------------

class OracleRuntime:
    """Duck-types IrisRuntime. ``encode`` must be given exactly the reference frames of a known
    scene (so no target reaches the scene) and "predicts" their true poses, re-based to the first
    one given and scaled by 0.5; ``locate`` gives the true pose of a photo of the scene in that
    frame, and must be asked about targets only; ``render`` returns the true image of whichever
    frame has the pose, after checking that it is not a reference. Records the order of the
    frames encoded and located."""

    image_size = SIZE
    near, far = 0.1, 1.0
    unit_range = (near, far)               # the cameras' unit: the default rule

    def __init__(self, scenes):
        self.truth = [(s.images, s.world_from_cam) for s in scenes]
        self.calls = 0
        self.encoded, self.located = [], []

    @staticmethod
    def _frames(ims, images):
        found = [np.flatnonzero((ims == im).all(axis=(1, 2, 3))) for im in images]
        return [int(f[0]) for f in found if f.size]

    def encode(self, images):
        images = np.stack(images)
        for ims, poses in self.truth:
            match = self._frames(ims, images)
            if len(match) == len(images):
                refs, _ = split_frames(len(ims))
                assert sorted(match) == list(refs), "encode was given other frames than the references"
                all_poses = np.linalg.inv(poses[match[0]]) @ poses
                all_poses[:, :3, 3] *= 0.5
                self.encoded.append(match)
                return SimpleNamespace(world_from_cam=all_poses[match], views=match,
                                       all_poses=all_poses, all_images=ims)
        raise AssertionError("unknown images")

    def locate(self, scene, images):
        match = self._frames(scene.all_images, images)
        assert len(match) == len(images) and not set(match) & set(scene.views), \
            "locate was asked about a reference or a photo of another scene"
        self.located.append(match)
        return scene.all_poses[match]

    def render(self, scene, pose, *, height, width, depth):
        assert (height, width) == SIZE and depth
        self.calls += 1
        k = int(np.argmin(np.abs(scene.all_poses - pose).sum(axis=(1, 2))))
        assert k not in scene.views, "a target was rendered from itself"
        image = scene.all_images[k]
        return SimpleNamespace(image=image, image_float=image / 255.0, depth=np.full(SIZE, 0.5))


def test_evaluate_with_oracle_runtime_is_perfect_in_both_orders():
    scenes = [rotation_scene(1), synthetic_or_fake_scene()]
    rt = OracleRuntime(scenes)
    results = evaluate(rt, scenes, progress=False)
    check_structure(results)
    assert rt.calls == 2 * 2 * 3
    for order in ORDERS:
        m = results[order]["model"]
        assert m["psnr"] == 100.0 and m["ssim"] == pytest.approx(1.0)
        assert all(m[k] == 1.0 for k in RPA_KEYS + LOCATE_KEYS)
    assert results["seq"]["baselines"] == results["rand"]["baselines"]
    # Seq: references and targets as stored; Rand: in the order of the scene's permutation.
    refs, targets = split_frames(8)
    assert rt.encoded[0] == list(refs) and rt.located[0] == list(targets)
    perm = rand_permutation(8, 0).tolist()
    assert rt.encoded[1] == [f for f in perm if f in refs] and rt.encoded[1][0] in refs
    assert rt.located[1] == [f for f in perm if f in targets]


def test_presentation_order():
    refs, targets = split_frames(8)
    assert presentation_order("seq", refs, targets, 5) == (list(refs), list(targets))
    for index in range(6):
        r, t = presentation_order("rand", refs, targets, index)
        perm = rand_permutation(8, index).tolist()
        assert sorted(r) == list(refs) and sorted(t) == list(targets)
        assert r == [f for f in perm if f in refs] and t == [f for f in perm if f in targets]
    assert len({tuple(presentation_order("rand", refs, targets, k)[0]) for k in range(6)}) > 1
    with pytest.raises(ValueError, match="order"):
        presentation_order("sideways", refs, targets, 0)


def test_locate_rpa_counts_pairs_with_a_target():
    """Targets' poses wrong, references right: RPA over all 28 pairs keeps the 10 reference pairs,
    locate RPA (the 18 pairs with a target) is 0; and the other way round."""
    from iris_train.evaluate import _locate_rpa
    scene = rotation_scene()
    refs, targets = split_frames(8)
    wrong = scene.world_from_cam.copy()
    for k, t in enumerate(targets):          # every pair with a target off by more than 50 deg
        wrong[t, :3, :3] = rot_y(100.0 * (k + 1))
    assert rpa(wrong, scene.world_from_cam)["rpa@5"] == pytest.approx(10 / 28)
    assert _locate_rpa(wrong, scene.world_from_cam, targets) == {k: 0.0 for k in LOCATE_KEYS}
    assert _locate_rpa(scene.world_from_cam, scene.world_from_cam, targets) == \
        {k: 1.0 for k in LOCATE_KEYS}


# ----------------------------------------------------------------------------------------------
# evaluate() on a random tiny model
# ----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny_results(tmp_path_factory):
    no_cameras = rotation_scene(2)
    no_cameras.world_from_cam = None
    scenes = [synthetic_or_fake_scene(), rotation_scene(3), no_cameras]
    grid = tmp_path_factory.mktemp("eval") / "grid.png"
    return evaluate(tiny_model(), scenes, progress=False, grid=grid), grid, scenes


def test_evaluate_tiny_model_structure_and_ranges(tiny_results):
    results, grid, _ = tiny_results
    check_structure(results)
    json.dumps(results, allow_nan=False)
    has_depth = getattr(tiny_results[2][0], "depth", None) is not None   # else a made-up scene
    for R in results.values():
        for name, values in [("model", R["model"]), *R["baselines"].items()]:
            for key, v in values.items():
                if (key == "depth_spearman" and not has_depth) or key in HEAD_KEYS:
                    assert v is None          # HEAD_KEYS: model cameras are the head's
                    continue
                assert v is not None and np.isfinite(v), (name, key)
                if key == "psnr":
                    assert 0 < v <= 100
                else:
                    assert 0 <= v <= 1 if "rpa@" in key else -1 <= v <= 1
    # Baselines see the same frames in either order.
    assert results["seq"]["baselines"] == results["rand"]["baselines"]
    assert grid.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "nearest reference" in format_table(results)


class DepthOracleRuntime(OracleRuntime):
    """Also "renders" the true depth of the matched frame, in other units (2 z + 0.1: a monotone
    map, so its rank correlation with the truth is exactly 1)."""

    def __init__(self, scenes):
        super().__init__(scenes)
        self.depth_of = [getattr(s, "depth", None) for s in scenes]

    def render(self, scene, pose, *, height, width, depth):
        result = super().render(scene, pose, height=height, width=width, depth=depth)
        image = result.image
        for (ims, _), true_depth in zip(self.truth, self.depth_of):
            match = np.flatnonzero((ims == image).all(axis=(1, 2, 3)))
            if match.size and true_depth is not None:
                result.depth = 2.0 * true_depth[match[0]] + 0.1
        return result


def scene_with_depth(seed):
    scene = rotation_scene(seed)
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.3, 1.0, (8, *SIZE))
    depth[:, :3] = 0.0                                       # rows without geometry
    scene.depth = depth
    return scene


def test_depth_spearman_in_evaluate_counts_only_scenes_with_depth():
    with_depth = scene_with_depth(11)
    no_depth = rotation_scene(12)                            # no depth attribute at all
    none_depth = rotation_scene(13)
    none_depth.depth = None
    results = evaluate(DepthOracleRuntime([with_depth, no_depth, none_depth]),
                       [with_depth, no_depth, none_depth], progress=False)
    for order in ORDERS:
        assert results[order]["model"]["depth_spearman"] == pytest.approx(1.0, abs=1e-12)
    results = evaluate(OracleRuntime([no_depth]), [no_depth], progress=False)
    assert all(results[o]["model"]["depth_spearman"] is None for o in ORDERS)
    assert "DEPTH-RHO" in format_table(results)


def test_true_depth_follows_the_image_crop():
    from iris_train.evaluate import _true_depth_and_K
    scene = scene_with_depth(14)
    big = np.repeat(np.repeat(scene.depth, 2, 1), 3, 2)     # 32 x 48: centre crop 32 x 32, halved
    scene.depth = big
    scene.images = np.repeat(np.repeat(scene.images, 2, 1), 3, 2)
    depth, K = _true_depth_and_K(scene, 8, SIZE)
    assert depth.shape == (8, *SIZE) and K is None
    crop = big[:, :, 8:40]
    np.testing.assert_array_equal(depth, crop[:, ::2, ::2])


def test_identity_baseline_in_evaluate(tiny_results):
    results, _, scenes = tiny_results
    # Scenes with cameras: the synthetic one translates (identity poses get 0 on every pair), the
    # rotation scene scores identity_rpa_of_rotation_scene(); the camera-less scene does not count.
    translating = rpa(np.broadcast_to(np.eye(4), (8, 4, 4)), scenes[0].world_from_cam)
    expected = identity_rpa_of_rotation_scene()
    for order in ORDERS:
        got = results[order]["baselines"]["identity_poses"]
        for k in RPA_KEYS:
            assert got[k] == pytest.approx((expected[k] + translating[k]) / 2)


def test_scenes_with_too_few_frames_are_skipped():
    scene = rotation_scene()
    short = SimpleNamespace(images=scene.images[:5], world_from_cam=scene.world_from_cam[:5])
    with pytest.raises(ValueError, match="no scene with at least 8 frames"):
        evaluate(OracleRuntime([scene]), [short], progress=False)


def test_write_json_is_atomic_and_strict(tmp_path):
    path = tmp_path / "sub" / "r.json"
    write_json(path, {"a": 1.0})
    assert json.loads(path.read_text()) == {"a": 1.0}
    with pytest.raises(ValueError):
        write_json(path, {"a": float("nan")})
    assert json.loads(path.read_text()) == {"a": 1.0}
    assert [p.name for p in path.parent.iterdir()] == ["r.json"]


# ----------------------------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------------------------

def test_help_runs():
    out = subprocess.run([sys.executable, "-m", "iris_train.evaluate", "--help"], cwd=ROOT,
                         capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr
    assert "MODEL" in out.stdout and "--json" in out.stdout and "synthetic:heldout" in out.stdout


def test_cli_on_a_folder_without_cameras(tmp_path, capsys):
    from PIL import Image
    ckpt = tmp_path / "model.pt"
    save_checkpoint(ckpt, tiny_model())
    folder = tmp_path / "data" / "scene_a"
    folder.mkdir(parents=True)
    for k, im in enumerate(rotation_scene(4).images):
        Image.fromarray(np.repeat(np.repeat(im, 2, 0), 3, 1)).save(folder / f"{k:03d}.png")  # 32x48
    out_json, grid = tmp_path / "eval.json", tmp_path / "grid.png"
    assert main([str(ckpt), str(tmp_path / "data"), "--json", str(out_json), "--grid", str(grid),
                 "--no-progress"]) == 0
    results = json.loads(out_json.read_text())
    check_structure(results)
    for R in results.values():
        assert np.isfinite(R["model"]["psnr"]) and np.isfinite(R["baselines"]["mean_colour"]["ssim"])
        assert all(R["model"][k] is None for k in RPA_KEYS + LOCATE_KEYS)
        assert R["baselines"]["nearest_reference"] == {"psnr": None, "ssim": None}
    assert grid.is_file()
    printed = capsys.readouterr().out
    assert "Seq" in printed and "Rand" in printed and str(out_json) in printed


@pytest.mark.slow
def test_exported_runtime_gives_the_torch_numbers(tmp_path, request):
    """The same evaluation through iris_runtime (exported ONNX graphs) and through torch.

    Minutes on a busy 2-core machine: runs only when asked for (``pytest -m slow``)."""
    if "slow" not in (request.config.getoption("markexpr") or ""):
        pytest.skip("slow (export + two evaluations): run with -m slow")
    pytest.importorskip("onnx")
    export = pytest.importorskip("export.pipeline")
    from iris_train.evaluate import load_evaluable
    model = tiny_model()
    out = export.export_model(model, tmp_path / "out", progress=False, quick=True, threads=1)
    scenes = [synthetic_or_fake_scene(), rotation_scene(6)]
    via_torch = evaluate(model, scenes, progress=False)
    via_runtime = evaluate(load_evaluable(out, threads=1), scenes, progress=False)
    for order in ORDERS:
        a, b = via_torch[order], via_runtime[order]
        assert a["baselines"] == b["baselines"]
        assert a["model"]["psnr"] == pytest.approx(b["model"]["psnr"], abs=1e-2)
        assert a["model"]["ssim"] == pytest.approx(b["model"]["ssim"], abs=1e-3)
        for k in RPA_KEYS:      # float32 graphs vs torch: at most one pair of 28 may cross a threshold
            assert a["model"][k] == pytest.approx(b["model"][k], abs=1 / 28 / 2 + 1e-9)
        for k in LOCATE_KEYS:   # ... of the 18 pairs with a target
            assert a["model"][k] == pytest.approx(b["model"][k], abs=1 / 18 / 2 + 1e-9)


def test_cli_reports_bad_inputs_in_one_line(tmp_path, capsys):
    assert main([str(tmp_path / "missing.pt"), "synthetic:heldout", "--no-progress"]) == 2
    assert "missing.pt" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty"), "synthetic:heldout"]) == 2
    assert "iris.json" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# The best-reference baseline, per-scene records, camera sources and --cameras true
# ----------------------------------------------------------------------------------------------

def test_best_reference_matches_a_brute_force_search():
    from iris_train.evaluate import best_reference
    from iris_train.metrics import psnr
    rng = np.random.default_rng(7)
    base = rng.uniform(0, 1, (*SIZE, 3))
    # Frames are the base image plus noise of different strengths, so the best one is not the
    # nearest index; frame 5 equals target 6 exactly (the PSNR cap decides, not inf).
    images = np.stack([np.clip(base + rng.normal(0, s, base.shape), 0, 1)
                       for s in (0.3, 0.05, 0.2, 0.01, 0.1, 0.5, 0.4, 0.02)])
    distinct = images.copy()
    images[5] = images[6]
    refs, targets = split_frames(8)
    expected = []
    for t in targets:
        best, best_score = None, -np.inf
        for r in refs:                                 # ties go to the earlier reference
            score = min(psnr(images[r], images[t]), 100.0)
            if score > best_score:
                best, best_score = r, score
        expected.append(best)
    assert best_reference(images, refs, targets) == expected == [3, 3, 5]
    # evaluate() reports it per scene (with the frames copied) and as a mean over scenes (the
    # oracle runtime tells frames apart by their pixels: no duplicate there).
    scene = rotation_scene(8)
    scene.images = np.rint(distinct * 255).astype(np.uint8)
    results = evaluate(OracleRuntime([scene]), [scene], progress=False)
    gt = scene.images / 255.0
    picked = best_reference(gt, refs, targets)
    want = np.mean([min(psnr(gt[r], gt[t]), 100.0) for r, t in zip(picked, targets)])
    for order in ORDERS:
        record = results[order]["scenes"][0]["baselines"]["best_reference"]
        assert record["frames"] == picked and record["psnr"] == pytest.approx(want)
        assert results[order]["baselines"]["best_reference"]["psnr"] == pytest.approx(want)
    assert "best reference" in format_table(results)


@dataclasses.dataclass
class OracleScene:
    """An ``OracleRuntime`` scene with the ``iris_runtime.Scene`` fields that ``evaluate`` reads
    and ``RuntimeBackend.with_cameras`` replaces."""
    world_from_cam: np.ndarray
    views: list
    all_poses: np.ndarray
    all_images: np.ndarray
    focal: np.ndarray = dataclasses.field(default_factory=lambda: np.array([1.2, 1.2]))
    K: np.ndarray | None = None
    encoder_focal: np.ndarray | None = None
    camera_source: str = "model"
    encoder_world_from_cam: np.ndarray | None = None


def test_scene_records_say_where_the_cameras_came_from(monkeypatch):
    """A solve that leaves two references to the camera head ("mixed"): the records name them,
    count them as fallbacks, and the summary adds them up; model cameras: no flags."""
    import iris_runtime.cameras as C
    from iris_train.evaluate import format_scenes

    class SolvedRuntime(OracleRuntime):
        default_cameras = "solve"

        def encode(self, images, cameras=None):
            assert cameras == "model"               # iris-eval solves the photos itself
            plain = super().encode(images)
            return OracleScene(plain.world_from_cam, plain.views, plain.all_poses, plain.all_images)

    def mixed_solve(photos, world_from_cam, focal, image_size, depth_range):
        assert len(photos) == 5 and image_size == SIZE
        poses = np.array(world_from_cam)
        poses[[1, 2, 4], :3, 3] += 0.01         # views 1, 2, 4 "solved", 3 and 0 not changed
        status = ("solved", "solved", "located", "unposed", "solved")
        return C.ModelCameras(poses, np.asarray(focal), None, "mixed", status, SIZE, None)

    monkeypatch.setattr(C, "replace_model_cameras", mixed_solve)
    scenes = [rotation_scene(9), rotation_scene(10)]
    results = evaluate(SolvedRuntime(scenes), scenes, progress=False, locate="model")
    refs, targets = split_frames(8)
    for order in ORDERS:
        R = results[order]
        assert R["cameras"]["sources"] == {"mixed": 2}
        assert R["cameras"]["fallbacks"] == 2 and R["cameras"]["scenes_with_fallbacks"] == 2
        for k, s in enumerate(R["scenes"]):
            c = s["cameras"]
            ref_order, _ = presentation_order(order, refs, targets, k)
            kept = {ref_order[3]}                   # presentation position 3 not posed
            assert c["source"] == "mixed" and c["fallbacks"] == 1
            assert c["references_solved"] == [f not in kept for f in refs]
            assert c["targets_located"] is None and s["name"] == f"scene {k}"   # model locate
    table = format_scenes(results)
    assert "mixed" in table and table.count("4/5") == 4
    plain = evaluate(OracleRuntime(scenes), scenes, progress=False)
    assert all(s["cameras"]["references_solved"] is None and s["cameras"]["fallbacks"] == 0
               for s in plain["seq"]["scenes"])


def test_grid_and_records_show_the_camera_head_beside_the_solve(tmp_path, monkeypatch):
    """The runtime path with a camera head that is wrong on two references and a solve that is
    right: the records score both on the reference pairs (the head's against an independent
    computation from its poses), and the grid's camera picture draws the three sets."""
    import iris_runtime.cameras as C
    from iris_train.evaluate.report import format_cameras

    class HeadRuntime(OracleRuntime):
        """An oracle whose camera head turns the references at positions 1 and 3."""
        default_cameras = "solve"

        def __init__(self, scenes):
            super().__init__(scenes)
            self.heads = []                                  # per encode: Seq, then Rand

        def encode(self, images, cameras=None):
            plain = super().encode(images)
            self.clean = plain.world_from_cam
            head = plain.world_from_cam.copy()
            head[1, :3, :3] = rot_x(40.0) @ head[1, :3, :3]
            head[3, :3, :3] = rot_y(-50.0) @ head[3, :3, :3]
            self.heads.append(head)
            return OracleScene(head, plain.views, plain.all_poses, plain.all_images)

    def perfect_solve(photos, world_from_cam, focal, image_size, depth_range):
        np.testing.assert_array_equal(world_from_cam, rt.heads[-1])   # the head's, replaced
        return C.ModelCameras(rt.clean, np.asarray(focal), None, "solve", ("solved",) * 5,
                              SIZE, None)

    monkeypatch.setattr(C, "replace_model_cameras", perfect_solve)
    panels = record_camera_panels(monkeypatch)
    scene = rotation_scene(23)
    rt = HeadRuntime([scene])
    grid = tmp_path / "grid.png"
    results = evaluate(rt, [scene], progress=False, locate="model", grid=grid)
    assert grid.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    refs, _ = split_frames(8)
    want = rpa(rt.heads[0], scene.world_from_cam[list(refs)])   # Seq: presentation = frames
    record = results["seq"]["scenes"][0]["model"]
    assert {k: record[f"head_reference_{k}"] for k in want} == want
    assert want["rpa@30"] < 1.0 and all(record[k] == 1.0 for k in REFERENCE_KEYS)
    assert results["seq"]["model"]["head_reference_rpa@30"] == want["rpa@30"]
    assert "the camera head's" in format_cameras(results)[0]
    check_head_panel(panels, scene.world_from_cam, refs, rt.heads[0])
    assert panels[0][1]["source"] == "solve"


def plane_scene(size=64, views=8, seed=3):
    """8 photos of a textured plane (z = 2 in the world) from cameras moving sideways and
    turning a little (a few pixels of flow a frame, which DIS follows), rendered exactly by ray
    casting; true poses, K and depth."""
    rng = np.random.default_rng(seed)
    import cv2
    texture = cv2.GaussianBlur(rng.uniform(0, 1, (512, 512, 3)).astype(np.float32), (0, 0), 3.0)
    texture = 255 * (texture - texture.min()) / (texture.max() - texture.min())
    H = W = size
    K = np.array([[1.2 * W, 0, W / 2], [0, 1.2 * H, H / 2], [0, 0, 1.0]])
    v, u = np.mgrid[0:H, 0:W] + 0.5
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    images, poses, depths = [], [], []
    for k in range(views):
        T = pose(rot_y(0.3 * k - 1.0) @ rot_x(0.5 * (k % 3) - 0.5), (0.05 * k - 0.2, 0.01 * k, 0.0))
        d = rays @ T[:3, :3].T
        lam = (2.0 - T[2, 3]) / d[..., 2]
        X = T[:3, 3] + lam[..., None] * d
        map_x = ((X[..., 0] + 1.5) / 3.0 * 512 - 0.5).astype(np.float32)
        map_y = ((X[..., 1] + 1.5) / 3.0 * 512 - 0.5).astype(np.float32)
        images.append(np.clip(cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR), 0, 255).astype(np.uint8))
        poses.append(T)
        depths.append(lam * rays[..., 2])
    return SimpleNamespace(images=np.stack(images), world_from_cam=np.stack(poses), K=K,
                           depth=np.stack(depths))


def rot_x(deg):
    a = np.radians(deg)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def test_true_cameras_are_the_true_ones_rebased_and_scaled():
    from iris_runtime.cameras import DEPTH_TARGET
    from iris_train.evaluate import true_cameras
    scene = plane_scene()
    refs, _ = split_frames(8)
    for ref_order in (list(refs), presentation_order("rand", refs, (1, 4, 6), 2)[0]):
        tc = true_cameras(scene.images, scene.world_from_cam, scene.K, ref_order, (0.1, 1.0))
        rebased = np.linalg.inv(scene.world_from_cam[ref_order[0]]) @ scene.world_from_cam
        np.testing.assert_allclose(tc.world_from_cam[:, :3, :3], rebased[:, :3, :3], atol=1e-12)
        np.testing.assert_allclose(tc.world_from_cam[:, :3, 3], tc.scale * rebased[:, :3, 3], atol=1e-12)
        np.testing.assert_array_equal(tc.world_from_cam[ref_order[0]], np.eye(4))
        np.testing.assert_allclose(tc.focal, [1.2, 1.2])
        assert tc.scale_source == "matches" and tc.principal_offset.tolist() == [0.0, 0.0]
        # The rule: the median depth of the scene (here the true depth maps of the references)
        # lands DEPTH_TARGET of the way into [near, far].
        target = 0.1 + DEPTH_TARGET * 0.9
        assert tc.scale * np.median(scene.depth[list(refs)]) == pytest.approx(target, rel=0.03)
        if ref_order == list(refs):
            seq = tc
    assert tc.scale == pytest.approx(seq.scale, rel=1e-12)     # nor on the order (but rounding)
    # Neither the world frame nor its unit changes the result.
    M = pose(rot_y(40.0) @ rot_x(-25.0), (3.0, -1.0, 7.0))
    moved = M @ scene.world_from_cam
    moved[:, :3, 3] *= 3.7
    again = true_cameras(scene.images, moved, scene.K, list(refs), (0.1, 1.0))
    np.testing.assert_allclose(again.world_from_cam, seq.world_from_cam, atol=1e-9)


def test_true_focal_follows_the_crop_to_model_resolution():
    from iris_train.evaluate import prepare_scene
    scene = plane_scene(size=32)
    scene.images = np.repeat(scene.images, 2, axis=2)[:, :, :48]      # 32 x 48 photos
    scene.K = np.array([[40.0, 0, 24.0], [0, 40.0, 16.0], [0, 0, 1]])
    prepared = prepare_scene(scene, 8, SIZE)
    # centre crop 32 x 32 (x0 = 8), then halved: fx 20, cx (24 - 8) / 2 = 8.
    np.testing.assert_allclose(prepared.K, np.broadcast_to([[20.0, 0, 8.0], [0, 20.0, 8.0], [0, 0, 1]],
                                                           (8, 3, 3)))


def check_true_run(results, n_scenes):
    for order in ORDERS:
        R = results[order]
        assert all(R["model"][k] == 1.0 for k in RPA_KEYS + LOCATE_KEYS)
        assert R["cameras"] == {"references": "true", "targets": "true", "sources": {"true": n_scenes},
                                "targets_epipolar": None, "fallbacks": 0, "scenes_with_fallbacks": 0}
        for s in R["scenes"]:
            assert s["cameras"]["source"] == "true" and s["cameras"]["scale_source"] == "matches"
            assert s["cameras"]["references_solved"] == [True] * 5
        assert 0 < R["model"]["psnr"] <= 100 and np.isfinite(R["model"]["ssim"])


def test_evaluate_with_true_cameras_on_a_torch_model(tmp_path, monkeypatch):
    from iris_train.evaluate import TorchBackend
    from iris_train.evaluate.cameras import pose_scene
    model = tiny_model()
    scene = plane_scene(size=SIZE[0] * 2)               # 32 x 32 photos, fitted to 16 x 16
    panels = record_camera_panels(monkeypatch)
    results = evaluate(model, [scene], progress=False, cameras="true", grid=tmp_path / "g.png")
    check_true_run(results, 1)
    # The encoded scene renders from exactly the true cameras, the targets at theirs.
    from iris_train.evaluate import prepare_scene
    p = prepare_scene(scene, 8, SIZE)
    refs, targets = split_frames(8)
    posed = pose_scene(TorchBackend(model), p, refs, targets, "true", "true")
    truth = true_cameras_of(p, refs)
    # The true cameras rounded once to the scene's float32: eps times their magnitude.
    atol = f32_tol(1, max(1.0, float(np.abs(truth.world_from_cam).max())))
    np.testing.assert_allclose(posed.encoded.world_from_cam.numpy(), truth.world_from_cam[list(refs)],
                               atol=atol)
    np.testing.assert_allclose(posed.encoded.focal.numpy(), truth.focal,
                               atol=f32_tol(1, max(1.0, float(np.max(truth.focal)))))
    # The references' rows went through the scene's float32 (one rounding, relative error <= u;
    # this was held by assert_allclose's default rtol of 1e-7 under an atol of 1e-12).
    np.testing.assert_allclose(posed.world_from_cam, truth.world_from_cam, atol=0, rtol=EPS32)
    # The camera head's cameras of the references are kept beside the true ones, scored on the
    # reference pairs and drawn in the grid. Encoded here again (another batch, perhaps another
    # order of the views): equal up to the encoder's float32 rounding (tests/tolerances.py,
    # ~3e-5; a camera of another view is off by > 1e-2).
    with torch.no_grad():
        head = model.encode(torch.from_numpy(p.images[list(refs)]).permute(0, 3, 1, 2).float()
                            / 255.0).world_from_cam.double().numpy()
    head_tol = encoder_tol(model.cfg, len(refs), "cameras", max(1.0, float(np.abs(head).max())))
    np.testing.assert_allclose(posed.head_world_from_cam[list(refs)], head, atol=head_tol)
    assert np.isnan(posed.head_world_from_cam[list(targets)]).all()
    np.testing.assert_allclose(posed.encoded.subset([3, 1]).encoder_world_from_cam.numpy(),
                               head[[3, 1]], atol=head_tol)
    want = {f"head_reference_{k}": v for k, v in rpa(head, p.poses[list(refs)]).items()}
    record = results["seq"]["scenes"][0]["model"]
    assert {k: record[k] for k in HEAD_KEYS} == want
    assert all(record[k] == 1.0 for k in REFERENCE_KEYS)
    assert all(results[o]["model"][k] is not None for o in ORDERS for k in HEAD_KEYS)
    check_head_panel(panels, p.poses, refs, head, head_tol)
    # With the model's own cameras the head is what is rendered: the same score, no head keys.
    plain = evaluate(model, [scene], progress=False, cameras="model")["seq"]["scenes"][0]["model"]
    assert {f"head_{k}": plain[k] for k in REFERENCE_KEYS} == want
    assert all(plain[k] is None for k in HEAD_KEYS)


def record_camera_panels(monkeypatch) -> list:
    """Every ``camera_panel`` call of ``evaluate``'s grid: ``(args, kwargs, picture)``."""
    import iris_train.evaluate.evaluation as E
    calls, real = [], E.camera_panel

    def recording(*args, **kwargs):
        picture = real(*args, **kwargs)
        calls.append((args, kwargs, picture))
        return picture
    monkeypatch.setattr(E, "camera_panel", recording)
    return calls


def check_head_panel(panels, gt_poses, refs, head, atol=1e-6):
    """One grid's camera picture with three sets: the rendered, the true and the head's cameras
    (``head`` [5, 4, 4], the references' in frame order, within ``atol``: float64 heads are
    exact, a torch model's float32 head is re-encoded by the caller), the head's drawn in
    green."""
    from iris_runtime.camera_plot import OTHER_COLOUR
    assert len(panels) == 1
    (_, _, gt, *_), kwargs, picture = panels[0]
    np.testing.assert_array_equal(gt, gt_poses)
    given = kwargs["head_poses"]
    assert np.flatnonzero(np.isfinite(given).all(axis=(1, 2))).tolist() == list(refs)
    np.testing.assert_allclose(given[list(refs)], head, atol=atol)
    green = (np.abs(picture.astype(int) - OTHER_COLOUR).sum(-1) < 30).sum()
    assert green > 50, "the camera head's cameras are not in the picture"


def true_cameras_of(prepared, refs):
    from iris_train.evaluate import true_cameras
    return true_cameras(prepared.images, prepared.poses, prepared.K, list(refs), (0.1, 1.0),
                        prepared.photos, prepared.photo_K)


def test_evaluate_with_true_cameras_on_an_exported_model(model_dir):
    """The exported-model path: the runtime's Scene gets the true cameras and focal, the render
    runs, and the cameras equal the torch path's."""
    from iris_runtime import IrisRuntime
    from iris_train.evaluate import RuntimeBackend, prepare_scene
    from iris_train.evaluate.cameras import pose_scene
    rt = IrisRuntime(model_dir, threads=1)
    scene = plane_scene(size=rt.image_size[0])
    check_true_run(evaluate(rt, [scene], progress=False, cameras="true"), 1)
    p = prepare_scene(scene, 8, rt.image_size)
    refs, targets = split_frames(8)
    posed = pose_scene(RuntimeBackend(rt), p, refs, targets, "true", "true")
    truth = true_cameras_of(p, refs)
    np.testing.assert_allclose(posed.encoded.world_from_cam, truth.world_from_cam[list(refs)], atol=1e-12)
    np.testing.assert_allclose(posed.encoded.focal, truth.focal, atol=1e-12)
    assert posed.encoded.encoder_focal is not None          # locate still recognises the images
    rt.locate(posed.encoded, p.images[1])
    # The camera head's poses ride along in the runtime's Scene (encoder_world_from_cam).
    head = rt.encode(list(p.images[list(refs)]), cameras="model").world_from_cam
    np.testing.assert_array_equal(posed.encoded.encoder_world_from_cam, head)
    np.testing.assert_array_equal(posed.head_world_from_cam[list(refs)], head)


def test_true_cameras_bad_arguments(tmp_path, capsys):
    from iris_runtime.errors import InputError
    no_cameras = rotation_scene(14)
    no_cameras.world_from_cam = None
    with pytest.raises(InputError, match=r"scene 0 \(scene 0\): cameras: 'true' needs"):
        evaluate(OracleRuntime([no_cameras]), [no_cameras], progress=False, cameras="true")
    with pytest.raises(InputError, match="locate: 'true' needs cameras='true'"):
        evaluate(OracleRuntime([no_cameras]), [no_cameras], progress=False, locate="true")
    with pytest.raises(InputError, match="cameras: expected one of"):
        evaluate(OracleRuntime([no_cameras]), [no_cameras], progress=False, cameras="colmap")
    with pytest.raises(InputError, match="locate: expected one of"):
        evaluate(OracleRuntime([no_cameras]), [no_cameras], progress=False, locate="sfm")
    # The CLI on a folder without cameras: one line, exit 2.
    from PIL import Image
    ckpt = tmp_path / "model.pt"
    save_checkpoint(ckpt, tiny_model())
    folder = tmp_path / "data" / "scene_a"
    folder.mkdir(parents=True)
    for k, im in enumerate(rotation_scene(4).images):
        Image.fromarray(im).save(folder / f"{k:03d}.png")
    assert main([str(ckpt), str(tmp_path / "data"), "--cameras", "true", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("iris-eval: error: scene 0 (scene_a)") and len(err.splitlines()) == 1


def test_synthetic_sets_give_the_solve_photos_at_their_own_resolution():
    """iris-eval's synthetic sets: the model's images at its size, the photos (what the camera
    solve sees) at SYNTHETIC_PHOTO_SIZE, the true K of each in its own pixels."""
    pytest.importorskip("pyrender")
    from iris_train.evaluate import SYNTHETIC_SETS, load_scenes, prepare_scene
    from iris_train.evaluate.scenes import SYNTHETIC_PHOTO_SIZE
    assert {"synthetic:capture-heldout", "synthetic:capture-validation"} <= set(SYNTHETIC_SETS)
    for data in ("synthetic:heldout", "synthetic:capture-heldout", "synthetic:capture-validation"):
        scenes, count = load_scenes(data, (64, 64), limit=1)
        assert count == 1
        p = prepare_scene(next(iter(scenes)), 8, (64, 64))
        assert p.images.shape == (8, 64, 64, 3)
        assert all(ph.shape == (*SYNTHETIC_PHOTO_SIZE, 3) for ph in p.photos)
        scale = SYNTHETIC_PHOTO_SIZE[0] / 64
        np.testing.assert_allclose(p.photo_K[:, :2, :3], scale * p.K[:, :2, :3], rtol=1e-9)


def test_grid_of_another_scene(tmp_path):
    from iris_runtime.errors import InputError
    scenes = [rotation_scene(21), rotation_scene(22)]
    grid = tmp_path / "grid.png"
    evaluate(OracleRuntime(scenes), scenes, progress=False, grid=grid, grid_scene=1, total=2)
    assert grid.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(InputError, match="grid_scene"):
        evaluate(OracleRuntime(scenes), scenes, progress=False, grid=grid, grid_scene=2, total=2)

"""scripts/head_distill.py: a short run trains the encoder and the camera head only, on the
solve's cameras, and writes a loadable checkpoint and a log with held-out scores."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from . import conftest
import torch

from .tolerances import f32_tol

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "models" / "iris-tiny-rgb.pt"
G1 = ROOT / "models" / "iris-tiny-rgb.train.pt"          # one encoder for the head and renderer


def _script():
    return conftest.load_script("head_distill")


@pytest.mark.skipif(not (SHIPPED.exists() and G1.exists()), reason="needs the checkpoints")
@pytest.mark.parametrize("init,augment", [
    (SHIPPED, []), (SHIPPED, ["--augment-rotation", "8"]),
    (SHIPPED, ["--capture", "2", "--capture-share", "0.25"]),
    (G1, []), (G1, ["--separate-encoder"])])
def test_head_distill_trains_the_encoder_and_head_only(tmp_path, monkeypatch, init, augment):
    from iris_train import load_model
    monkeypatch.setenv("IRIS_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "run"
    assert _script().main(["--out", str(out), "--classic", "2", "--steps", "2", "--batch", "1",
                           "--eval-every", "1", "--heldout-scenes", "1", "--init", str(init),
                           "--camera-head", "correlation", *augment]) == 0
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [e["step"] for e in log] == [0, 1, 2]
    # Every scene turned is zoomed: its focal is not the scene's and does not train.
    assert set(log[-1]["train"]) == ({"solve_rot", "solve_trans"} if "--augment-rotation" in augment
                                     else {"solve_rot", "solve_trans", "solve_focal"})
    assert 0.0 <= log[-1]["heldout"]["rpa@15"] <= 1.0
    # With capture-like training scenes the capture-like held-out ones are scored too.
    assert ("capture_heldout" in log[-1]["heldout"]) == ("--capture" in augment)
    trained, shipped = load_model(out / "last.pt"), load_model(init)
    assert trained.cfg.camera_head == "correlation"
    assert trained.cfg.camera_encoder == (init == SHIPPED or "--separate-encoder" in augment)
    before, after = shipped.state_dict(), trained.state_dict()
    # The encoder the head reads trains; the renderer (and, where the head has an encoder of its
    # own, the encoder the renderer reads) stays as it was.
    head_encoder = "camera_encoder." if trained.cfg.camera_encoder else "encoder."
    kept = ("field", "renderer") + (("encoder",) if trained.cfg.camera_encoder else ())
    for name in kept:
        for key, value in getattr(shipped, name).state_dict().items():
            assert torch.equal(value, after[f"{name}.{key}"]), key
    # (A head's new encoder starts as the init's encoder.)
    start = {k: before.get(k, before.get("encoder." + k.removeprefix("camera_encoder.")))
             for k in after if k.startswith(head_encoder)}
    moved = [k for k, v in start.items() if not torch.equal(v, after[k])]
    assert moved, "the head's encoder did not train"


def _blob_images(X: torch.Tensor, world_from_cam: torch.Tensor, focal: float, size: int = 64):
    """One Gaussian blob per view where the world point ``X [3]`` projects (pixel centres at
    +0.5, principal point at the centre, ``focal`` fx / W) -> ``[V, 3, size, size]``, and the
    projections ``[V, 2]``."""
    cam = torch.linalg.inv(world_from_cam) @ torch.cat([X, torch.ones(1)])
    uv = focal * size * cam[:, :2] / cam[:, 2:3] + size / 2
    grid = torch.arange(size, dtype=torch.float32) + 0.5
    d2 = (grid[None, None, :] - uv[:, 0, None, None]) ** 2 \
        + (grid[None, :, None] - uv[:, 1, None, None]) ** 2
    return torch.exp(-d2 / (2 * 1.5 ** 2))[:, None].repeat(1, 3, 1, 1), uv


def _centroids(images: torch.Tensor) -> torch.Tensor:
    size = images.shape[-1]
    w = images[:, 0]
    grid = torch.arange(size, dtype=torch.float32) + 0.5
    total = w.sum((1, 2))
    return torch.stack([(w.sum(1) * grid).sum(1) / total, (w.sum(2) * grid).sum(1) / total], 1)


def _triangulate(uv: np.ndarray, world_from_cam: np.ndarray, focal_px: float, size: int):
    """Linear (DLT) triangulation of one point seen at pixels ``uv [V, 2]``."""
    rows = []
    for (u, v), T in zip(uv, world_from_cam):
        K = np.array([[focal_px, 0, size / 2], [0, focal_px, size / 2], [0, 0, 1]])
        P = K @ np.linalg.inv(T)[:3]
        rows += [u * P[2] - P[0], v * P[2] - P[1]]
    X = np.linalg.svd(np.array(rows))[2][-1]
    return X[:3] / X[3]


def _reprojected_blobs(images: torch.Tensor, world_from_cam: torch.Tensor, focal: torch.Tensor):
    """One point's blob centroids ``uv [V, 2]`` in 64x64 ``images``, triangulated with the given
    cameras and focal and reprojected -> (reprojected [V, 2], uv)."""
    uv = _centroids(images).double().numpy()
    Tn, f_px = world_from_cam.double().numpy(), float(focal[0]) * 64
    cam = np.linalg.inv(Tn) @ np.append(_triangulate(uv, Tn, f_px, 64), 1.0)
    return f_px * cam[:, :2] / cam[:, 2:3] + 32, uv


@pytest.mark.parametrize("seed", range(6))
def test_augment_moves_the_images_as_the_cameras_say(seed):
    """The augmented photos are what the augmented cameras (and focal) see: a point's blobs in
    the four augmented views, triangulated with the augmented cameras, reproject onto themselves to
    a fifth of a pixel (a wrong roll sign is pixels off), and each blob's distance from the centre
    grows by the focal's factor."""
    from iris_runtime.orbit import look_at
    rng = np.random.default_rng(seed)
    centre = np.zeros(3)
    eyes = [np.array([0.6 * np.sin(a), -0.6 * np.cos(a), 0.15]) for a in rng.uniform(-0.4, 0.4, 4)]
    T = np.stack([look_at(e, centre, np.array([0.0, 0.0, -1.0])) for e in eyes])
    T = torch.as_tensor(np.linalg.inv(T[0]) @ T, dtype=torch.float32)
    X = torch.as_tensor(np.array([0.08, 0.05, 0.6]) + rng.normal(0, 0.02, 3), dtype=torch.float32)
    images, _ = _blob_images(X, T, 1.0)
    aug_images, aug_T, aug_focal = _script().augment(images, T, torch.full((2,), 1.0), rng, 15.0)
    assert torch.allclose(aug_T[0], torch.eye(4), atol=1e-5)
    assert torch.allclose(torch.linalg.det(aug_T[:, :3, :3]), torch.ones(4), atol=1e-5)
    reprojected, uv = _reprojected_blobs(aug_images, aug_T, aug_focal)
    assert np.abs(reprojected - uv).max() < 0.2, (reprojected, uv)
    # mirror and roll keep a point's distance from the centre; the zoom scales it as the focal
    ratio = (_centroids(aug_images) - 32).norm(dim=1) / (_centroids(images) - 32).norm(dim=1)
    assert torch.allclose(ratio, aug_focal[0] / 1.0 * torch.ones(4), atol=0.02), ratio
    # and the augmentation did something: rolled or mirrored views differ from the originals
    assert not torch.allclose(_centroids(aug_images), _centroids(images), atol=0.5)


@pytest.mark.parametrize("seed", range(6))
def test_augment_rotation_moves_the_images_as_the_cameras_say(seed):
    """``augment_rotation`` turns each camera about its centre: a point's blobs in the warped and
    area-averaged views, triangulated with the augmented cameras and focal, reproject onto
    themselves to a quarter of a pixel at 64x64 (a transposed rotation is pixels off); the
    cameras' centres keep their distances (a pure rotation moves no centre); every view turned."""
    from iris_runtime.orbit import look_at
    rng = np.random.default_rng(seed)
    eyes = [np.array([0.6 * np.sin(a), -0.6 * np.cos(a), 0.15]) for a in rng.uniform(-0.4, 0.4, 4)]
    T = np.stack([look_at(e, np.zeros(3), np.array([0.0, 0.0, -1.0])) for e in eyes])
    T = torch.as_tensor(np.linalg.inv(T[0]) @ T, dtype=torch.float32)
    X = torch.as_tensor(np.array([0.03, 0.02, 0.6]) + rng.normal(0, 0.02, 3), dtype=torch.float32)
    blobs, _ = _blob_images(X, T, 1.0, size=256)
    photos = (blobs.permute(0, 2, 3, 1) * 255).round().to(torch.uint8).numpy()
    images, aug_T, aug_focal, zoom = _script().augment_rotation(
        photos, T, torch.full((2,), 1.0), (64, 64), rng, 10.0)
    assert images.shape == (4, 3, 64, 64) and zoom > 1.0
    assert torch.allclose(aug_T[0], torch.eye(4), atol=1e-5)
    assert torch.allclose(torch.linalg.det(aug_T[:, :3, :3]), torch.ones(4), atol=1e-5)
    assert torch.allclose(aug_focal, torch.full((2,), zoom))
    reprojected, uv = _reprojected_blobs(images, aug_T, aug_focal)
    assert np.abs(reprojected - uv).max() < 0.25, (reprojected, uv)
    centres, aug_centres = T[:, :3, 3], aug_T[:, :3, 3]
    assert torch.allclose(torch.cdist(centres, centres), torch.cdist(aug_centres, aug_centres),
                          atol=1e-5)
    turned = torch.linalg.inv(T) @ aug_T            # relative to the original, per view
    assert not torch.allclose(turned[1:, :3, :3], turned[:1, :3, :3].expand(3, 3, 3), atol=1e-3)


def test_direction_loss_is_scale_free_and_sees_a_reversed_baseline():
    rng = np.random.default_rng(0)
    T = torch.eye(4).repeat(5, 1, 1)
    T[:, :3, 3] = torch.as_tensor(rng.normal(size=(5, 3)), dtype=torch.float32)
    loss = _script().direction_loss
    scaled = T.clone()
    scaled[:, :3, 3] *= 7.0
    # 1 - cos in float32: the baselines (1 rounding), two norms and a dot product of 3 terms, a
    # square root and a division: ~10 roundings of values <= 1 (tests/tolerances.py, 9.2e-7).
    # A 1-degree direction error costs 1.5e-4.
    tol = f32_tol(10)
    assert float(loss(T, T)) < tol and float(loss(scaled, T)) < tol
    mirrored = T.clone()
    mirrored[:, :3, 3] *= -1.0                       # every baseline reversed: 1 - cos = 2
    assert float(loss(mirrored, T)) == pytest.approx(2.0, abs=f32_tol(10, 2.0))
    moved = T.clone()
    moved[1, :3, 3] += 0.5
    assert 1e-3 < float(loss(moved, T)) < 2.0


def _heldout_rpa():
    return conftest.load_script("heldout_rpa")


def test_fit_scores_a_head_against_the_teacher_by_baseline():
    """``heldout_rpa.fit``: a head that returns the teacher's cameras fits perfectly; one that
    returns identities fails on rotation, worst where the teacher's baselines are longest."""
    from iris_runtime.orbit import look_at
    from iris_train.pseudo_poses import SolvedCameras
    hr = _heldout_rpa()
    angles = np.radians([0, 3, 8, 15, 25, 40])
    eyes = [np.array([0.6 * np.sin(a), -0.6 * np.cos(a), 0.1]) for a in angles]
    T = np.stack([look_at(e, np.zeros(3), np.array([0.0, 0.0, -1.0])) for e in eyes])
    T = np.linalg.inv(T[0]) @ T
    solved = SolvedCameras(T, 1.0, np.ones(6, bool))
    scenes = [type("S", (), {"images": np.zeros((6, 64, 64, 3), np.uint8)})()]

    class Head:
        def __init__(self, cams):
            self.cams = torch.as_tensor(cams, dtype=torch.float32)[None]

        def encode_batch(self, x):
            return None, self.cams, torch.ones(1, 2)

    perfect = hr.fit(Head(T), scenes, lambda i: solved, [0])
    assert perfect["rpa@5"] == 1.0 and perfect["median_rotation_error"] < 1e-2
    identity = hr.fit(Head(np.tile(np.eye(4), (6, 1, 1))), scenes, lambda i: solved, [0])
    quarters = identity["by_baseline"]
    assert len(quarters) == 4 and quarters[0]["baseline"][0] < quarters[-1]["baseline"][1]
    rot = [q["median_rotation_error"] for q in quarters]
    assert rot == sorted(rot) and rot[-1] > 20.0 and identity["rpa@15"] < 0.5


def test_separate_camera_encoder_keeps_the_renderer_and_takes_the_head(tmp_path, torch_export_rgb):
    """``ship_checkpoint.py --camera-head-from``: the merged model's features (what the renderer
    reads) are bit for bit the source's and its cameras the other checkpoint's; it exports and
    its graphs match torch (``iris-export``'s validation).

    The source's field and renderer are those of the session's random explicit-colour model
    (conftest ``torch_export_rgb``, whose config this one is but for the camera head), so the
    export traces the two encoder graphs only and takes the renderer graphs from that export;
    its validation holds them to the merged model as it would traced ones."""
    import dataclasses
    import subprocess
    import sys

    from iris_train import build_model, load_model
    from iris_train.model import save_checkpoint

    from .conftest import copy_graphs_from
    twin_dir, twin = torch_export_rgb
    cfg = dataclasses.replace(twin.cfg, camera_head="correlation")
    torch.manual_seed(1)
    renderer = build_model(cfg).eval()
    renderer.field.load_state_dict(twin.field.state_dict())
    renderer.renderer.load_state_dict(twin.renderer.state_dict())
    torch.manual_seed(2)
    cameras = build_model(cfg).eval()
    with torch.no_grad():                # cameras a little off the identity
        for p in cameras.camera_head.parameters():
            p.add_(0.01 * torch.randn_like(p))
    save_checkpoint(tmp_path / "r.pt", renderer)
    save_checkpoint(tmp_path / "c.pt", cameras)
    subprocess.run([sys.executable, str(ROOT / "scripts" / "ship_checkpoint.py"),
                    str(tmp_path / "r.pt"), str(tmp_path / "m.pt"),
                    "--camera-head-from", str(tmp_path / "c.pt")], check=True, cwd=ROOT)
    merged = load_model(tmp_path / "m.pt")
    assert merged.cfg.camera_encoder and merged.camera_encoder is not None
    images = torch.rand(1, 5, 3, 64, 64)
    with torch.no_grad():
        f_m, T_m, k_m = merged.encode_batch(images)
        f_r, _, _ = renderer.encode_batch(images)
        _, T_c, k_c = cameras.encode_batch(images)
    assert torch.equal(f_m, f_r) and torch.equal(T_m, T_c) and torch.equal(k_m, k_c)
    assert (T_m[0, 1:, :3, 3].abs() > 1e-4).any()
    # Merging again from the merged checkpoint (a camera encoder of its own) gives the same.
    subprocess.run([sys.executable, str(ROOT / "scripts" / "ship_checkpoint.py"),
                    str(tmp_path / "r.pt"), str(tmp_path / "m2.pt"),
                    "--camera-head-from", str(tmp_path / "m.pt")], check=True, cwd=ROOT)
    again = load_model(tmp_path / "m2.pt")
    for k, v in merged.state_dict().items():
        assert torch.equal(v, again.state_dict()[k]), k
    from export import pipeline
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pipeline, "export_graph",
                   copy_graphs_from(twin_dir, trace=("encoder", "encoder_cameras")))
        pipeline.export_model(tmp_path / "m.pt", tmp_path / "out", quick=True, progress=False,
                              threads=1)
    manifest = json.loads((tmp_path / "out" / "iris.json").read_text())
    assert set(manifest["graphs"]) == {"encoder", "encoder_cameras", "renderer", "renderer_views"}
    assert all(manifest["validation"][g]["passed"] for g in manifest["graphs"])
    from iris_runtime import IrisRuntime
    rt = IrisRuntime(tmp_path / "out", threads=1)
    x = (images[0].permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8)
    scene = rt.encode(list(x), cameras="model")
    with torch.no_grad():
        _, T_q, _ = merged.encode_batch(torch.from_numpy(x).permute(0, 3, 1, 2)[None].float() / 255)
    assert np.abs(scene.world_from_cam - T_q[0].double().numpy()).max() < 1e-4

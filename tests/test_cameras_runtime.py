"""The camera solve inside the runtime: the intrinsics carried from the photos to the model's
resolution, ``IrisRuntime.encode(images, cameras="solve")`` and ``locate`` on photos at their
own resolution, the Scene's record of them, iris-render's ``--cameras`` and iris-eval's torch
backend."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from iris_runtime.cameras import replace_model_cameras, solve_cameras
from iris_runtime.errors import ImageError, InputError
from iris_runtime.images import (camera_copies, fit_to_model, fit_to_working_size,
                                 plan_crop_resize)

from . import np_scenes
from .tolerances import encoder_tol

REPO = Path(__file__).resolve().parents[1]
SIZE = (192, 256)
FOCAL = 230.0
DEPTH_RANGE = (0.1, 1.0)


def _angle_deg(Ra, Rb):
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


@pytest.fixture(scope="module")
def corner():
    """Six ray-cast photos of a textured corner (192x256) and their true cameras."""
    truth = np_scenes.cameras(6, 70.0)
    return np_scenes.render(truth, FOCAL, SIZE), truth


# ----------------------------------------------------------------------------------------------
# intrinsics from the photos to the model's resolution (torch-free)
# ----------------------------------------------------------------------------------------------

def _project(K, Y):
    return (Y @ K.T)[:, :2] / Y[:, 2:]


@pytest.mark.parametrize("photo_size", [(250, 333), (768, 1024), (64, 64), (301, 200)])
def test_camera_copies_carry_the_intrinsics_to_the_model(photo_size):
    """A point seen at pixel p in the photo lands at crop-resize(p) in the model's image: the
    model's K (model_from_camera @ K of the solve's copy) must project it there. Checked against
    the direct computation from the photo's own K and the documented crop/resize formula."""
    rng = np.random.default_rng(0)
    h, w = photo_size
    K_photo = np.array([[0.9 * w, 0, w / 2], [0, 0.9 * w, h / 2], [0, 0, 1.0]])
    photos = [np.zeros((h, w, 3), np.uint8)] * 2
    copies, model_from_camera = camera_copies(photos, (64, 64))
    hc, wc = copies[0].shape[:2]
    assert max(hc, wc) == min(512, max(h, w)) and abs(hc / wc - h / w) < 2 / min(hc, wc)
    # The solve's K lives in the copy: the photo's K scaled by the copy's size.
    K_copy = np.diag([wc / w, hc / h, 1.0]) @ K_photo
    K_model = model_from_camera @ K_copy
    # Direct: the model image is the centre crop of the photo resized to 64x64.
    crop = min(h, w)
    x0, y0 = (w - crop) // 2, (h - crop) // 2
    s = 64 / crop
    K_direct = np.array([[s * K_photo[0, 0], 0, s * (K_photo[0, 2] - x0)],
                         [0, s * K_photo[1, 1], s * (K_photo[1, 2] - y0)], [0, 0, 1.0]])
    np.testing.assert_allclose(K_model, K_direct, rtol=1e-12, atol=1e-9)
    Y = np.c_[rng.uniform(-1, 1, (20, 2)), rng.uniform(2, 4, 20)]
    plan = plan_crop_resize(h, w, 64, 64)
    np.testing.assert_allclose(_project(K_model, Y), plan.to_output(_project(K_photo, Y)),
                               atol=1e-9)


def test_camera_copies_of_photos_of_different_sizes_share_one_camera():
    photos = [np.zeros((480, 640, 3), np.uint8), np.zeros((600, 600, 3), np.uint8)]
    copies, model_from_camera = camera_copies(photos, (64, 64))
    assert {c.shape for c in copies} == {(480, 480, 3)}        # the model's aspect, one size
    np.testing.assert_allclose(model_from_camera, np.diag([64 / 480, 64 / 480, 1.0]), atol=1e-12)


def test_fit_to_working_size_bounds_the_longer_side_and_refuses_bad_input():
    big = np.zeros((600, 1000, 3), np.uint8)
    out, plan = fit_to_working_size(big)
    assert out.shape == (307, 512, 3) and (plan.x0, plan.y0) == (0, 0)
    small = np.ones((100, 80, 3), np.uint8)
    out, plan = fit_to_working_size(small)
    np.testing.assert_array_equal(out, small)
    assert out is not small
    for bad in (np.zeros((10, 10), np.uint8), np.zeros((10, 10, 3), np.float32), "photo.png"):
        with pytest.raises(ImageError, match="image"):
            fit_to_working_size(bad)
    with pytest.raises(ImageError, match="max_side"):
        fit_to_working_size(small, 0)


def test_replace_model_cameras_keeps_the_model_for_an_unposable_view_0(corner):
    photos, truth = corner
    model = np.tile(np.eye(4), (4, 1, 1))
    model[:, :3, 3] = np.arange(12).reshape(4, 3) * 0.01
    flat = np.full_like(photos[0], 90)
    out = replace_model_cameras([flat, *photos[:3]], model, [1.1, 1.2], (64, 64), DEPTH_RANGE)
    assert out.source == "model" and out.status == ("unposed",) * 4 and out.solve is None
    np.testing.assert_array_equal(out.world_from_cam, model)
    np.testing.assert_array_equal(out.focal, [1.1, 1.2])
    # A posable view 0 and an unposable other: that view keeps the model's camera.
    out = replace_model_cameras([*photos[:3], flat], model, [1.1, 1.2], (64, 64), DEPTH_RANGE)
    assert out.source == "mixed" and out.status == ("solved",) * 3 + ("unposed",)
    np.testing.assert_array_equal(out.world_from_cam[3], model[3])
    np.testing.assert_array_equal(out.world_from_cam[0], np.eye(4))
    assert out.camera_size == SIZE


# ----------------------------------------------------------------------------------------------
# IrisRuntime (an exported random model: the cameras do not depend on its weights)
# ----------------------------------------------------------------------------------------------

def test_runtime_solves_the_cameras_on_the_photos_at_their_own_resolution(corner, model_dir):
    from iris_runtime import IrisRuntime
    photos, truth = corner
    rt = IrisRuntime(model_dir, threads=1)
    H, W = rt.image_size
    images = list(photos)
    model = rt.encode(images, cameras="model")
    epi = rt.encode(images, cameras="solve")
    assert model.camera_source == "model" and model.camera_size is None
    assert model.camera_status is None and model.camera_solve is None
    assert epi.camera_source == "solve" and epi.camera_size == SIZE
    assert epi.camera_status == ("solved",) * 6 and "camera_size=(192, 256)" in repr(epi)
    np.testing.assert_array_equal(epi.field_maps, model.field_maps)     # the encoder's, as always
    np.testing.assert_array_equal(epi.encoder_focal, model.focal)
    # The camera head's poses are kept beside the solve's (read-only, like every Scene array).
    np.testing.assert_array_equal(epi.encoder_world_from_cam, model.world_from_cam)
    assert not epi.encoder_world_from_cam.flags.writeable
    # The same solve as solve_cameras of the photos, its K carried to the model's resolution: bit
    # for bit on the same BLAS threads (the runtime's one; two round differently).
    from threadpoolctl import ThreadpoolController
    with ThreadpoolController().limit(limits=1, user_api="blas"):
        s = solve_cameras(images, (rt.near, rt.far))
    np.testing.assert_array_equal(epi.world_from_cam, s.world_from_cam)
    crop = plan_crop_resize(*SIZE, H, W)
    np.testing.assert_allclose(epi.K, crop.matrix @ s.K, rtol=1e-12)
    np.testing.assert_allclose(epi.focal, [epi.K[0, 0] / W, epi.K[1, 1] / H])
    rel = np.linalg.inv(truth[0]) @ truth
    for k in range(6):
        assert _angle_deg(epi.world_from_cam[k, :3, :3], rel[k, :3, :3]) < 2.0
    # locate: a view left out comes back at the camera the full solve gave it, at any size.
    left_out = epi.subset([0, 1, 2, 4, 5])
    assert left_out.camera_status == ("solved",) * 5 and left_out.camera_solve is epi.camera_solve
    np.testing.assert_array_equal(left_out.encoder_world_from_cam,
                                  model.world_from_cam[[0, 1, 2, 4, 5]])
    assert epi.subset([3, 1]).encoder_world_from_cam.shape == (2, 4, 4)
    assert model.subset([1, 0]).encoder_world_from_cam is None
    bigger = np.repeat(np.repeat(photos[3], 2, axis=0), 2, axis=1)       # the same photo, 2x
    for photo in (photos[3], bigger):
        T, status = rt.locate(left_out, photo, with_status=True)
        assert status == "located"
        assert _angle_deg(T[:3, :3], epi.world_from_cam[3, :3, :3]) < 1.0
        spread = np.linalg.norm(epi.world_from_cam[:, :3, 3], axis=1).mean()
        assert np.linalg.norm(T[:3, 3] - epi.world_from_cam[3, :3, 3]) < 0.05 * spread
    poses, status = rt.locate(left_out, [photos[3], np.full_like(photos[3], 90)],
                              with_status=True)
    assert status == ("located", "unposed")
    # The unposed photo gets the model's prediction (queries alone or together: float rounding).
    np.testing.assert_allclose(poses[1], rt.locate(model, [np.full_like(photos[3], 90)])[0],
                               atol=1e-5)
    assert rt.render(epi, 2).shape == (H, W, 3)


def test_runtime_refines_the_encoders_cameras(corner, model_dir, monkeypatch):
    """``encode(cameras="refined")`` starts ``refine_model_cameras`` from the encoder's cameras
    and focal with the photos in canonical order (here an encoder whose head is 5 degrees off
    the truth, the focal 10% off, as a trained head is): the cameras land within 2 degrees
    whatever the photos' order, the field maps stay the encoder's, the head's cameras are kept
    beside them and ``locate`` poses a left-out photo against the refinement's points."""
    import cv2

    from iris_runtime import IrisRuntime
    from iris_runtime.cameras import canonical_order, refine_model_cameras
    photos, truth = corner
    rt = IrisRuntime(model_dir, threads=1)
    H, W = rt.image_size
    crop = plan_crop_resize(*SIZE, H, W)
    K64 = crop.matrix @ np.array([[FOCAL, 0, SIZE[1] / 2], [0, FOCAL, SIZE[0] / 2], [0, 0, 1]])
    rng = np.random.default_rng(1)
    head = np.linalg.inv(truth[0]) @ truth
    for k in range(1, 6):
        axis = rng.normal(size=3)
        head[k, :3, :3] = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.radians(5.0))[0] \
            @ head[k, :3, :3]
    head_focal = np.array([1.1 * K64[0, 0] / W, 1.1 * K64[1, 1] / H], np.float32)
    run = rt._run_encoder

    given = {}

    def encoder(batch, is_ref):   # the head's cameras of all six in any order (its frame: the
        maps, poses, _ = run(batch, is_ref)                        # first's), its focal always
        if len(batch) == 6 and np.all(is_ref):
            rows = given.setdefault("rows", batch.copy())          # the first call: as given
            order = [next(k for k in range(6) if np.array_equal(row, rows[k])) for row in batch]
            poses = (np.linalg.inv(head[order[0]]) @ head[order]).astype(np.float32)
        return maps, poses, head_focal
    monkeypatch.setattr(rt, "_run_encoder", encoder)
    images = list(photos)
    model = rt.encode(images, cameras="model")
    got = rt.encode(images, cameras="refined")
    assert got.camera_source == "refined" and got.camera_status == ("solved",) * 6
    assert got.camera_size == SIZE
    np.testing.assert_array_equal(got.field_maps, model.field_maps)
    np.testing.assert_array_equal(got.encoder_world_from_cam, model.world_from_cam)
    np.testing.assert_array_equal(got.encoder_focal, model.focal)
    perm = canonical_order(images)
    start = np.empty((6, 4, 4))
    start[perm] = np.linalg.inv(head[perm[0]]) @ head[perm]
    want = refine_model_cameras(images, np.linalg.inv(start[0]) @ start, head_focal, (H, W),
                                (rt.near, rt.far))
    np.testing.assert_allclose(got.world_from_cam, want.world_from_cam, atol=1e-9)
    order = [4, 2, 0, 5, 1, 3]
    shuffled = rt.encode([images[k] for k in order], cameras="refined")
    np.testing.assert_allclose(shuffled.world_from_cam,
                               np.linalg.inv(got.world_from_cam[order[0]])
                               @ got.world_from_cam[order], atol=1e-6)
    rel = np.linalg.inv(truth[0]) @ truth
    for k in range(6):
        assert _angle_deg(got.world_from_cam[k, :3, :3], rel[k, :3, :3]) < 2.0
    assert got.K[0, 0] == pytest.approx(K64[0, 0], rel=0.03)
    T, status = rt.locate(got.subset([0, 1, 2, 4, 5]), photos[3], with_status=True)
    assert status == "located" and _angle_deg(T[:3, :3], rel[3, :3, :3]) < 2.0


def test_runtime_model_cameras_are_bitwise_unchanged(corner, model_dir):
    from iris_runtime import IrisRuntime
    photos, _ = corner
    rt = IrisRuntime(model_dir, threads=1)
    images = list(photos[:4])
    default, model = rt.encode(images), rt.encode(images, cameras="model")
    batch = rt._load_images(images)
    maps, poses, focal = rt._run_encoder(batch, np.ones(4, bool))      # the graph's own outputs
    for scene in (default, model):
        np.testing.assert_array_equal(scene.field_maps, maps)
        np.testing.assert_array_equal(scene.world_from_cam, poses.astype(np.float64))
        np.testing.assert_array_equal(scene.focal, focal.astype(np.float64))
        assert scene.camera_source == "model" and scene.encoder_focal is None
        assert scene.encoder_world_from_cam is None
    np.testing.assert_array_equal(rt.render(default, 1), rt.render(model, 1))


def test_refined_fallback_keeps_the_encoders_cameras_for_locate(model_dir, monkeypatch):
    """When ``encode(cameras="refined")`` falls back to the model's cameras (the refinement
    gives up and the solve cannot pose view 0), the Scene keeps the refinement's start (the
    camera head on the photos in canonical_order, another run with another focal) and beside it
    the encoder's own cameras of the photos as given, which ``locate`` checks the reference
    images against: it locates a photo as on the model's scene, and still refuses a scene whose
    reference images are not the ones it was encoded from."""
    import dataclasses
    from types import SimpleNamespace

    import iris_runtime.cameras.replace as replace
    from iris_runtime import IrisRuntime
    from iris_runtime.cameras import canonical_order, canonical_start
    rng = np.random.default_rng(0)
    photos = [rng.integers(0, 256, (64, 64, 3), dtype=np.uint8) for _ in range(4)]
    if np.array_equal(canonical_order(photos), np.arange(4)):
        photos = photos[::-1]             # the start must be a second run of the head
    monkeypatch.setattr(replace, "refine_cameras", lambda *a, **k: None)
    monkeypatch.setattr(replace, "solve_cameras",      # view 0 unposed: the model's cameras
                        lambda copies, depth_range: SimpleNamespace(status=("unposed",) * 4))
    rt = IrisRuntime(model_dir, threads=1)
    model = rt.encode(photos, cameras="model")
    scene = rt.encode(photos, cameras="refined")
    assert scene.camera_source == "model" and scene.camera_status == ("unposed",) * 4
    start, start_focal = canonical_start(
        photos, model.world_from_cam, model.focal,
        lambda perm: rt._run_cameras(model.reference_images[perm], np.ones(len(perm), bool)))
    np.testing.assert_array_equal(scene.world_from_cam, start)
    np.testing.assert_array_equal(scene.focal, start_focal)
    assert np.abs(scene.focal - model.focal).max() > 1e-6          # what locate cannot match
    np.testing.assert_array_equal(scene.encoder_focal, model.focal)
    np.testing.assert_array_equal(scene.encoder_world_from_cam, model.world_from_cam)
    np.testing.assert_array_equal(rt.locate(scene, photos[1]), rt.locate(model, photos[1]))
    refs = scene.reference_images.copy()
    refs[1] = 1.0 - refs[1]
    for bad in (dataclasses.replace(scene, reference_images=refs),
                dataclasses.replace(scene, reference_images=model.reference_images[::-1])):
        with pytest.raises(InputError, match="reference_images give focal"):
            rt.locate(bad, photos[1])


def test_bad_camera_values_raise_typed_errors(model_dir):
    from iris_runtime import IrisRuntime
    from iris_runtime.runtime import Scene
    rt = IrisRuntime(model_dir, threads=1)
    images = [np.zeros((64, 64, 3), np.uint8)] * 2
    for bad in ("Epipolar", "colmap", 1, ["model"]):
        with pytest.raises(InputError, match="cameras"):
            rt.encode(images, cameras=bad)
    scene = rt.encode(images, cameras="model")
    kwargs = dict(field_maps=scene.field_maps, world_from_cam=scene.world_from_cam,
                  focal=scene.focal, K=scene.K, image_size=scene.image_size)
    mirrored = np.tile(np.eye(4), (2, 1, 1))
    mirrored[1, 0, 0] = -1.0
    nan = np.tile(np.eye(4), (2, 1, 1))
    nan[1, 2, 3] = np.nan
    for name, value in (("camera_source", "colmap"), ("encoder_focal", [0.0, 1.0]),
                        ("camera_size", (0, 64)), ("camera_size", "64x64"),
                        ("camera_status", ("solved",)), ("camera_status", ("done", "solved")),
                        ("camera_solve", "solve"),
                        ("encoder_world_from_cam", np.tile(np.eye(4), (3, 1, 1))),   # V = 2
                        ("encoder_world_from_cam", np.eye(4)),
                        ("encoder_world_from_cam", mirrored), ("encoder_world_from_cam", nan),
                        ("encoder_world_from_cam", "poses")):
        with pytest.raises(InputError, match=name):
            Scene(**kwargs, **{name: value})
    # A good value is kept as a read-only float64 copy.
    given = np.tile(np.eye(4, dtype=np.float32), (2, 1, 1))
    kept = Scene(**kwargs, encoder_world_from_cam=given).encoder_world_from_cam
    assert kept.dtype == np.float64 and not kept.flags.writeable
    given[0, 0, 3] = 5.0
    assert kept[0, 0, 3] == 0.0


@pytest.mark.torch
def test_default_cameras_follow_the_manifest(corner, model_dir, tmp_path):
    """A model trained on solved cameras says so in its manifest ("cameras"), and encode,
    one-shot render and iris-eval then solve the cameras by default; without the key: "model"."""
    import shutil

    from iris_runtime import IrisRuntime
    from iris_train.evaluate import _backend
    from iris_train.model import trained_cameras
    photos, _ = corner
    d = tmp_path / "epi"
    shutil.copytree(model_dir, d)
    doc = json.loads((d / "iris.json").read_text())
    assert doc["cameras"] == "model"                  # a random model: no training config
    doc["cameras"] = "epipolar"                      # the solve's former name: an old manifest
    (d / "iris.json").write_text(json.dumps(doc))
    rt_model, rt_epi = IrisRuntime(model_dir, threads=1), IrisRuntime(d, threads=1)
    assert rt_model.default_cameras == "model" and rt_epi.default_cameras == "solve"
    images = list(photos[:5])
    default, epi = rt_epi.encode(images), rt_epi.encode(images, cameras="solve")
    assert default.camera_source == epi.camera_source == "solve"
    old = rt_epi.encode(images, cameras="epipolar")         # ... and an old request
    assert old.camera_source == "solve"
    np.testing.assert_array_equal(old.world_from_cam, epi.world_from_cam)
    np.testing.assert_array_equal(default.world_from_cam, epi.world_from_cam)
    assert rt_epi.encode(images, cameras="model").camera_source == "model"
    np.testing.assert_array_equal(rt_epi.render(images, np.eye(4)), rt_epi.render(default, 0))
    backend = _backend(rt_epi)
    # iris-eval's default is the manifest's; its backend encodes with the model's cameras and
    # solves the photos itself (evaluate.cameras.pose_scene).
    assert backend.default_cameras == "solve"
    assert backend.encode(np.stack(images)).camera_source == "model"
    del doc["cameras"]                                 # manifests written before the key
    (d / "iris.json").write_text(json.dumps(doc))
    assert IrisRuntime(d, threads=1).default_cameras == "model"
    # The checkpoint side: what the training config says, "model" when it says nothing.
    assert trained_cameras({"train_config": {"render_cameras": "solve"}}) == "solve"
    assert trained_cameras({"train_config": {"render_cameras": "epipolar"}}) == "solve"   # old
    assert trained_cameras({"train_config": {}}) == trained_cameras({}) == "model"


def test_cli_cameras_flag(corner, model_dir, tmp_path):
    from PIL import Image
    photos, _ = corner
    paths = []
    for k in range(4):
        p = tmp_path / f"{k}.png"
        Image.fromarray(photos[k]).save(p)
        paths.append(str(p))
    base = [sys.executable, "-c", "import sys; sys.modules['torch'] = None; "
            "from iris_runtime.cli import main; sys.exit(main())", str(model_dir), *paths]
    out = subprocess.run(base + ["-o", str(tmp_path / "o"), "--cameras", "solve", "--view", "1",
                                 "--no-depth"], capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert "cameras of the inputs: solve (every view solved from the photos at 256x192)" \
        in out.stdout and (tmp_path / "o" / "view_001.png").is_file()
    cams = json.loads((tmp_path / "o" / "cameras.json").read_text())
    assert cams["source"] == "solve" and cams["solved_at"] == [192, 256]
    assert cams["status"] == ["solved"] * 4 and len(cams["focal"]) == 2
    head = np.array(cams["encoder_world_from_cam"])           # the camera head's poses
    assert head.shape == (4, 4, 4)
    # View 0's pose is the identity by construction (camera_head.py's
    # world_from_cam_from_residual selects a constant eye), and JSON round-trips it: exact on
    # every CPU, where the former literal atol=1e-6 bounded nothing.
    np.testing.assert_array_equal(head[0], np.eye(4))
    plain = subprocess.run(base + ["-o", str(tmp_path / "m"), "--cameras", "model", "--view", "0",
                                   "--no-depth"], capture_output=True, text=True, cwd=REPO)
    assert plain.returncode == 0, plain.stderr
    cams = json.loads((tmp_path / "m" / "cameras.json").read_text())
    assert cams["source"] == "model" and cams["solved_at"] is None and cams["status"] is None
    # The camera head's float32 poses from a second process (ONNX Runtime, its default thread
    # pool): two evaluations of the encoder, equal up to its float32 rounding
    # (tests/tolerances.py encoder_tol, ~3e-5 for the tiny config; equal bit for bit here),
    # not a literal 1e-6 measured on one CPU. Another view's camera is off by > 1e-2.
    config = json.loads((model_dir / "iris.json").read_text())["config"]
    head_tol = encoder_tol(config, len(paths), "cameras", max(1.0, float(np.abs(head).max())))
    np.testing.assert_allclose(cams["encoder_world_from_cam"], head, atol=head_tol, rtol=0)
    bad = subprocess.run(base + ["-o", str(tmp_path / "p"), "--cameras", "sfm"],
                         capture_output=True, text=True, cwd=REPO)
    assert bad.returncode == 2 and "--cameras" in bad.stderr and len(bad.stderr.splitlines()) == 1


# ----------------------------------------------------------------------------------------------
# iris-eval --cameras solve (torch checkpoint backend)
# ----------------------------------------------------------------------------------------------

@pytest.mark.torch
def test_evaluate_with_solved_cameras_on_a_torch_model():
    """iris-eval solves the cameras from the photos at their own resolution (256 here) while the
    model sees its 64x64 images, exactly as IrisRuntime.encode does with a user's photos."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("pyrender")
    import dataclasses

    from iris_train import build_model, preset
    from iris_train.evaluate import ORDERS, TorchBackend, evaluate, prepare_scene
    from iris_train.evaluate.cameras import pose_scene
    from iris_train.synthetic import render_scene
    torch.manual_seed(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        cfg = dataclasses.replace(preset("tiny"), samples=4)
        model = build_model(cfg).eval()
        scene = render_scene(1_000_003, n_views=8, size=(256, 256))
        size = (cfg.image_height, cfg.image_width)
        prepared = prepare_scene(scene, 8, size)
        assert prepared.images.shape[1:3] == size and prepared.photos[0].shape[:2] == (256, 256)
        # One implementation: the references' cameras are replace_model_cameras of their photos.
        backend = TorchBackend(model)
        refs, targets = (0, 2, 3, 5, 7), (1, 4, 6)
        posed = pose_scene(backend, prepared, refs, targets, "solve", "solve")
        plain = backend.encode(prepared.images[list(refs)])
        ref = replace_model_cameras([prepared.photos[r] for r in refs], backend.poses(plain),
                                    plain.focal.double().numpy(), size, (cfg.near, cfg.far))
        assert ref.camera_size == (256, 256) and ref.source == posed.source == "solve"
        np.testing.assert_array_equal(posed.encoded.world_from_cam.numpy(),
                                      ref.world_from_cam.astype(np.float32))
        np.testing.assert_array_equal(posed.encoded.focal.numpy(), ref.focal.astype(np.float32))
        assert posed.targets_located[list(targets)].all() and posed.fallbacks == 0
        base = evaluate(model, [scene], progress=False)
        got = evaluate(model, [scene], progress=False, cameras="solve")
        for order in ORDERS:
            assert "cameras" not in base[order]
            c = got[order]["cameras"]
            assert c["references"] == c["targets"] == "solve"
            assert c["sources"] == {"solve": 1} and c["targets_epipolar"] == 1.0
            for k in ("rpa@15", "rpa@30", "locate_rpa@30"):
                assert got[order]["model"][k] > base[order]["model"][k]
            assert got[order]["model"]["rpa@15"] == 1.0
        with pytest.raises(ValueError, match="cameras"):
            evaluate(model, [scene], progress=False, cameras="colmap")
    finally:
        torch.set_num_threads(threads)


# ----------------------------------------------------------------------------------------------
# the training teacher (iris_train.pseudo_poses): the same solve, on the largest photos
# ----------------------------------------------------------------------------------------------

@pytest.mark.torch
def test_teacher_solves_on_the_largest_photos_and_caches_per_training_size(corner, tmp_path,
                                                                           monkeypatch):
    pytest.importorskip("torch")
    import cv2

    from iris_train import pseudo_poses as PP
    photos, truth = corner

    class Scenes:
        """A dataset that trains at 48x64 and keeps 192x256 renders (as SyntheticScenes with a
        larger render_size does)."""
        seeds, n_views, size, cache_dir = [7], 6, (48, 64), tmp_path

        def cached(self, seed):
            return type("S", (), {"images": photos})()

        def __getitem__(self, i):
            small = np.stack([cv2.resize(p, (64, 48), interpolation=cv2.INTER_AREA)
                              for p in photos])
            return type("S", (), {"images": small})()

    scenes = Scenes()
    solved = PP.load_or_solve(scenes, 0, DEPTH_RANGE)
    s = solve_cameras(list(photos), DEPTH_RANGE)                  # on the 192x256 photos
    assert solved.solved.all()
    np.testing.assert_array_equal(solved.world_from_cam, s.world_from_cam)
    assert solved.focal == pytest.approx(s.focal / SIZE[1], rel=1e-12)   # fx/W at 48x64
    teacher = PP.load_or_estimate(scenes, 0)
    assert teacher.trusted.sum() == 30 and teacher.focal == solved.focal
    rel = np.linalg.inv(s.world_from_cam[2]) @ s.world_from_cam[1]
    np.testing.assert_allclose(teacher.cam_from_cam[1, 2][:3, :3], rel[:3, :3], atol=1e-12)
    assert abs(np.linalg.norm(teacher.cam_from_cam[1, 2][:3, 3]) - 1) < 1e-12
    assert (teacher.inliers[teacher.trusted] > 0).all()
    # Cached: read back without solving again; another training size solves again.
    monkeypatch.setattr(PP, "solve_cameras", lambda *a, **k: pytest.fail("solved again"))
    again = PP.load_or_solve(scenes, 0, DEPTH_RANGE)
    np.testing.assert_array_equal(again.world_from_cam, solved.world_from_cam)
    assert PP.load_or_estimate(scenes, 0).focal == teacher.focal
    scenes.size = (96, 128)
    with pytest.raises(pytest.fail.Exception, match="solved again"):
        PP.load_or_solve(scenes, 0, DEPTH_RANGE)


@pytest.mark.torch
def test_teacher_store_names_a_folder_for_each_dataset_it_keeps(tmp_path):
    """The store's folder names what the cameras depend on: the classic scenes, the capture-like
    ones (a kind drawn per seed: the newest of their generator versions) and a single kind; a
    mix of kinds is not kept."""
    pytest.importorskip("torch")
    from iris_train import pseudo_poses as PP
    from iris_train.data import SyntheticScenes
    from iris_train.synthetic import CAPTURE_KINDS, KIND_VERSIONS
    v, solve = max(KIND_VERSIONS[k] for k in CAPTURE_KINDS), PP.SOLVE_VERSION
    kw = dict(size=(64, 64), render_size=(256, 256), cache_dir=tmp_path)
    assert PP.store_folder(SyntheticScenes(range(3), **kw), (64, 64), tmp_path).name == \
        f"classic-1_256x256_to_64x64_v8_solve{solve}"
    assert PP.store_folder(SyntheticScenes(range(3), kind="capture", **kw), (64, 64),
                           tmp_path).name == f"capture-{v}_256x256_to_64x64_v8_solve{solve}"
    assert PP.store_folder(SyntheticScenes(range(3), kind="orbit", **kw), (64, 64),
                           tmp_path).name == \
        f"orbit-{KIND_VERSIONS['orbit']}_256x256_to_64x64_v8_solve{solve}"
    assert PP.store_folder(SyntheticScenes(range(3), kind={"orbit": 1, "walk": 1}, **kw),
                           (64, 64), tmp_path) is None


@pytest.mark.torch
def test_teacher_store_packs_whole_blocks_and_serves_them_without_solving(corner, tmp_path,
                                                                          monkeypatch):
    """``pseudo_poses.pack`` gathers the per-scene solved cameras of whole blocks of seeds into
    one store file that ``load_or_solve`` reads back bit for bit with the per-scene files gone;
    a store of another solve version is not used."""
    pytest.importorskip("torch")
    from iris_train import pseudo_poses as PP
    photos, _ = corner

    class Scenes:
        """Three single-kind synthetic-like scenes (seeds 4, 5, 6) kept at the photos' size."""
        seeds, n_views, size, render_size, kind = [4, 5, 6], 6, SIZE, SIZE, None
        cache_dir = tmp_path / "cache"

        def kind_of(self, seed):
            return None

        def cached(self, seed):
            return type("S", (), {"images": photos[::-1] if seed == 5 else photos})()

    scenes, store = Scenes(), tmp_path / "store"
    scenes.cache_dir.mkdir()
    solved = {s: PP.load_or_solve(scenes, i, DEPTH_RANGE, store_dir=store)
              for i, s in enumerate(scenes.seeds)}
    assert not np.allclose(solved[4].world_from_cam, solved[5].world_from_cam)
    written = PP.pack(scenes, DEPTH_RANGE, store, block=2)
    # Blocks are [4, 5] and [6, 7]: only the first is whole.
    assert [p.name for p in written] == ["seeds_0000004-0000005.npz"]
    assert PP.pack(scenes, DEPTH_RANGE, store, block=2) == []            # already packed
    for f in scenes.cache_dir.glob("solved_*"):
        f.unlink()
    monkeypatch.setattr(PP, "STORE_BLOCK", 2)
    monkeypatch.setattr(PP, "solve_cameras", lambda *a, **k: pytest.fail("solved again"))
    for i, s in enumerate(scenes.seeds[:2]):
        got = PP.load_or_solve(scenes, i, DEPTH_RANGE, store_dir=store)
        np.testing.assert_array_equal(got.world_from_cam, solved[s].world_from_cam)
        np.testing.assert_array_equal(got.solved, solved[s].solved)
        assert got.focal == solved[s].focal
    with pytest.raises(pytest.fail.Exception, match="solved again"):
        PP.load_or_solve(scenes, 2, DEPTH_RANGE, store_dir=store)        # not in a whole block
    with pytest.raises(pytest.fail.Exception, match="solved again"):     # another depth range
        PP.load_or_solve(scenes, 0, (0.2, 2.0), store_dir=store)
    monkeypatch.setattr(PP, "SOLVE_VERSION", PP.SOLVE_VERSION + 1)       # another solve
    with pytest.raises(pytest.fail.Exception, match="solved again"):
        PP.load_or_solve(scenes, 0, DEPTH_RANGE, store_dir=store)


def test_camera_work_runs_the_blas_on_the_runtimes_threads(corner, model_dir, monkeypatch):
    """``IrisRuntime(threads=1)`` finds cameras with numpy's BLAS on one thread (its default is
    one per core, which a busy machine makes several times slower,
    ``benchmarks/encode_threads.py``), and gives the BLAS its threads back afterwards; with
    ``threads=None`` the BLAS keeps its own setting."""
    from threadpoolctl import ThreadpoolController

    import iris_runtime.cameras.replace as replace
    from iris_runtime import IrisRuntime
    photos, _ = corner
    controller = ThreadpoolController()
    blas = [lib for lib in controller.info() if lib["user_api"] == "blas"]
    if not blas:
        pytest.skip("numpy has no BLAS threadpoolctl can see")
    before = [lib["num_threads"] for lib in blas]
    seen = []
    solve = replace.solve_cameras

    def spy(*args, **kwargs):
        seen.append([lib["num_threads"] for lib in ThreadpoolController().info()
                     if lib["user_api"] == "blas"])
        return solve(*args, **kwargs)

    monkeypatch.setattr(replace, "solve_cameras", spy)
    with controller.limit(limits=2, user_api="blas"):      # a BLAS with more than one thread
        outside = [lib["num_threads"] for lib in ThreadpoolController().info()
                   if lib["user_api"] == "blas"]
        IrisRuntime(model_dir, threads=1).encode(list(photos), cameras="solve")
        IrisRuntime(model_dir).encode(list(photos), cameras="solve")
        after = [lib["num_threads"] for lib in ThreadpoolController().info()
                 if lib["user_api"] == "blas"]
    assert seen == [[1] * len(blas), outside]
    assert after == outside
    assert [lib["num_threads"] for lib in ThreadpoolController().info()
            if lib["user_api"] == "blas"] == before

"""Tests of iris_runtime: IrisRuntime, Scene, the manifest checks, the orbit path and iris-render.

Model under test: ``IRIS_TEST_MODEL_DIR`` (an ``iris-export`` output directory) when set, which is
how these tests run in an environment without torch; otherwise, when torch is installed, a random
tiny model (``torch.manual_seed(0); build_model(preset("tiny"))``) exported once per session.
Tests marked ``torch`` compare with ``IrisModel`` and always use the exported random model.
Explicit colour (``preset("tiny-rgb")``, conftest ``rgb_model_dir``/``torch_export_rgb``): the
parity tests run on it too (``pair``), plus its own tests (the reference photos sampled in numpy:
subset, hand-built scenes, missing photos, chunking and culling).

Renders are kept small (a few hundred rays each): the renderer costs ~1-2 ms of CPU per ray.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from iris_runtime import (ImageError, InputError, IrisError, IrisRuntime, ManifestError,
                          ModelFileError, ModelFormatError, ModelIntegrityError, RenderResult,
                          Scene)
from iris_runtime import geometry as G
from iris_runtime.images import fit_to_model
from iris_runtime.orbit import orbit_poses

from .tolerances import encoder_terms, encoder_tol, f32_tol, render_tol, renderer_terms

REPO = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------------------------
# Fixtures
# ----------------------------------------------------------------------------------------------

# ``torch_export`` and ``model_dir`` (one exported model per session) live in tests/conftest.py.

@pytest.fixture(scope="session")
def rt(model_dir) -> IrisRuntime:
    return IrisRuntime(model_dir, threads=1)


def _images(n: int, size=(64, 64), seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (*size, 3), dtype=np.uint8) for _ in range(n)]


@pytest.fixture(scope="session")
def scene(rt) -> Scene:
    return rt.encode(_images(3, rt.image_size))


def _rotation(axis, angle) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx


def _pose(axis=(0.3, 1.0, 0.1), angle=0.05, t=(0.02, -0.01, 0.03)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _rotation(axis, angle)
    T[:3, 3] = t
    return T


#: A pose that sees part of the scene only: rays and samples outside every reference view exist,
#: so culling (skipped samples, views and rays) is exercised.
SIDEWAYS = _pose(axis=(0.0, 1.0, 0.0), angle=0.6, t=(0.25, 0.0, -0.05))


# ----------------------------------------------------------------------------------------------
# Parity with torch
# ----------------------------------------------------------------------------------------------

def _torch_scene(model, images):
    import torch
    x = np.stack(images).astype(np.float32).transpose(0, 3, 1, 2) * np.float32(1.0 / 255.0)
    with torch.no_grad():
        return model.encode(torch.from_numpy(x))


@pytest.fixture(scope="session")
def torch_pair(torch_export):
    """(runtime, runtime scene, IrisModel, torch scene) on the same images."""
    model_dir, model = torch_export
    runtime = IrisRuntime(model_dir, threads=1)
    images = _images(3, runtime.image_size, seed=1)
    return runtime, runtime.encode(images), model, _torch_scene(model, images)


@pytest.fixture(scope="session")
def torch_pair_rgb(torch_export_rgb):
    """``torch_pair`` for the random explicit-colour model (``tiny-rgb``)."""
    model_dir, model = torch_export_rgb
    runtime = IrisRuntime(model_dir, threads=1)
    images = _images(3, runtime.image_size, seed=1)
    return runtime, runtime.encode(images), model, _torch_scene(model, images)


@pytest.fixture(scope="session")
def torch_pair_fine(torch_export_fine):
    """``torch_pair`` for the random model with finer field maps (``map_scale`` 2) and the
    colour deviation input."""
    model_dir, model = torch_export_fine
    runtime = IrisRuntime(model_dir, threads=1)
    images = _images(3, runtime.image_size, seed=1)
    return runtime, runtime.encode(images), model, _torch_scene(model, images)


@pytest.fixture(params=["tiny", "tiny-rgb", "tiny-rgb-fine"])
def pair(request):
    """``torch_pair``, ``torch_pair_rgb`` and ``torch_pair_fine`` in turn."""
    return request.getfixturevalue({"tiny": "torch_pair", "tiny-rgb": "torch_pair_rgb",
                                    "tiny-rgb-fine": "torch_pair_fine"}[request.param])


def _torch_render(model, tscene, pose, height, width):
    import torch
    with torch.no_grad():
        poses = torch.tensor(pose, dtype=torch.float32)[None]
        rgb, depth = model.render(tscene, poses, height, width)
    return rgb[0].numpy(), depth[0].numpy()


@pytest.mark.torch
def test_encode_matches_torch(torch_pair):
    _, scene, _, tscene = torch_pair
    assert np.abs(scene.world_from_cam - tscene.world_from_cam.double().numpy()).max() <= 1e-5
    assert np.abs(scene.focal - tscene.focal.double().numpy()).max() <= 1e-5
    assert np.abs(scene.field_maps - tscene.field_maps.numpy()).max() <= 1e-4
    assert np.abs(scene.K - tscene.intrinsics().double().numpy()).max() <= 1e-4


@pytest.mark.torch
@pytest.mark.parametrize("pose, size", [(_pose(), (16, 16)),      # model res is 64x64: smaller
                                        (SIDEWAYS, (12, 20)),     # other aspect, partial overlap
                                        (2, (12, 12))])           # pose of input view 2
def test_render_matches_torch(pair, pose, size):
    runtime, scene, model, tscene = pair
    res = runtime.render(scene, pose, height=size[0], width=size[1], depth=True)
    # An int pose is compared with torch rendering *its own* prediction of that view: the
    # geometric cue normalises t - s, which is discontinuous where the target centre meets a
    # reference centre, so torch fed ONNX's pose (1e-8 away from its own) would differ by ~1e-3.
    T = tscene.world_from_cam[pose].double().numpy() if isinstance(pose, int) else pose
    rgb, depth = _torch_render(model, tscene, T, *size)
    assert res.image_float.shape == (*size, 3) and res.depth.shape == size
    assert np.abs(res.image_float - rgb).max() <= 1e-4
    assert np.abs(res.depth - depth).max() <= 1e-4


@pytest.mark.torch
def test_subset_matches_torch(pair):
    runtime, scene, model, tscene = pair
    sub = scene.subset([2, 0])
    res = runtime.render(sub, _pose(angle=-0.05), height=12, width=12, depth=True)
    rgb, depth = _torch_render(model, tscene.subset([2, 0]), _pose(angle=-0.05), 12, 12)
    assert np.abs(res.image_float - rgb).max() <= 1e-4
    assert np.abs(res.depth - depth).max() <= 1e-4


@pytest.mark.torch
def test_locate_matches_torch(torch_pair):
    import torch
    runtime, scene, model, _ = torch_pair
    photos = _images(2, runtime.image_size, seed=7)
    x = np.stack(photos).astype(np.float32).transpose(0, 3, 1, 2) * np.float32(1.0 / 255.0)
    with torch.no_grad():
        want = model.locate(torch.from_numpy(scene.reference_images.copy()), torch.from_numpy(x))
    got = runtime.locate(scene, photos)
    assert got.shape == (2, 4, 4) and got.dtype == np.float64
    assert np.abs(got - want.double().numpy()).max() <= 1e-5


# ----------------------------------------------------------------------------------------------
# Runtime behaviour (no torch needed)
# ----------------------------------------------------------------------------------------------

def test_scene_is_immutable_and_typed(rt, scene):
    H, W = rt.image_size
    V = 3
    assert scene.num_views == V and scene.image_size == (H, W)
    assert scene.field_maps.dtype == np.float32 and scene.field_maps.ndim == 4
    assert scene.world_from_cam.dtype == np.float64 and scene.world_from_cam.shape == (V, 4, 4)
    assert scene.focal.shape == (2,) and scene.K.shape == (3, 3)
    # View 0's pose is the identity by construction, not by rounding (camera_head.py's
    # world_from_cam_from_residual selects a constant eye for view 0): exact on every CPU, where
    # the former literal atol=1e-6 bounded nothing.
    np.testing.assert_array_equal(scene.world_from_cam[0], np.eye(4))
    np.testing.assert_allclose(scene.K, G.intrinsics_from_focal(scene.focal, H, W))
    for name in ("field_maps", "world_from_cam", "focal", "K", "reference_images"):
        assert not getattr(scene, name).flags.writeable
    assert scene.reference_images.shape == (V, 3, H, W) and scene.reference_images.dtype == np.float32
    with pytest.raises(ValueError):
        scene.field_maps[0, 0, 0, 0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        scene.focal = np.ones(2)
    assert all(G.is_rigid(T) for T in scene.world_from_cam)


def test_subset_keeps_frame(scene):
    sub = scene.subset([2, 1])
    assert sub.num_views == 2
    np.testing.assert_array_equal(sub.world_from_cam, scene.world_from_cam[[2, 1]])
    np.testing.assert_array_equal(sub.field_maps, scene.field_maps[[2, 1]])
    np.testing.assert_array_equal(sub.K, scene.K)
    np.testing.assert_array_equal(sub.reference_images, scene.reference_images)   # all inputs: the frame
    for bad in ([], [3], [-1], [0, 0], ["a"]):
        with pytest.raises(InputError, match="indices"):
            scene.subset(bad)


def test_locate_returns_rigid_poses_and_leaves_the_scene(rt, scene):
    """locate: rigid finite world_from_cam, one photo -> [4, 4], a sequence -> [Q, 4, 4]; photos
    located together = one by one; the scene is not changed (field maps bitwise) and neither is a
    render made from it, whatever photo was located; a subset (same frame) locates the same."""
    photos = _images(3, (80, 60), seed=5)
    before = {k: getattr(scene, k).copy() for k in ("field_maps", "world_from_cam", "focal", "K")}
    render_before = rt.render(scene, _pose(), height=6, width=6, depth=True)
    one = rt.locate(scene, photos[0])
    many = rt.locate(scene, photos)
    assert one.shape == (4, 4) and many.shape == (3, 4, 4)
    assert one.dtype == np.float64 and np.isfinite(many).all()
    assert all(G.is_rigid(T) for T in many)
    # Queries never see each other: together = one by one (float rounding of other batch sizes:
    # the encoder's, tests/tolerances.py, ~3e-5 for poses of magnitude 1; a query seeing
    # another moves its pose by ~0.1).
    tol = encoder_tol(rt.manifest.config, scene.num_views + len(photos), "cameras",
                      max(1.0, float(np.abs(many).max())))
    assert np.abs(many[0] - one).max() <= tol
    assert np.abs(many[1:] - rt.locate(scene, photos[1:])).max() <= tol
    np.testing.assert_array_equal(rt.locate(scene.subset([2, 0]), photos), many)
    rt.locate(scene, [255 - p for p in photos])                    # other photos located
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(scene, k), v)
    render_after = rt.render(scene, _pose(), height=6, width=6, depth=True)
    np.testing.assert_array_equal(render_after.image_float, render_before.image_float)
    np.testing.assert_array_equal(render_after.depth, render_before.depth)


def test_encoder_isolates_references_in_the_runtime(rt):
    """Through the runtime's encoder session: the references' field maps and cameras are equal
    (up to the encoder's float32 rounding, tests/tolerances.py: another batch and other
    attention-row lengths may take other kernels; measured bitwise here) with queries present,
    changed or absent, and a render from the references made with queries present equals the
    render of the scene encoded alone (up to the encoder's and the renderer's rounding). A leak
    moves field maps, poses and renders by 1e-2 to 1e-1 (tests/test_model.py)."""
    refs = rt._load_images(_images(3, rt.image_size, seed=8))
    queries = rt._load_images(_images(2, rt.image_size, seed=9))
    alone = rt._run_encoder(refs, np.ones(3, bool))
    runs = [rt._run_encoder(np.concatenate([refs, q]), np.arange(5) < 3)
            for q in (queries, 1.0 - queries, queries[::-1])]
    config = rt.manifest.config
    for out in runs:
        for name, a, b in zip(("field_maps", "world_from_cam", "focal"), out, alone):
            rows = slice(None) if name == "focal" else slice(0, 3)
            output = {"world_from_cam": "cameras"}.get(name, name)
            tol = encoder_tol(config, 5, output, max(1.0, float(np.abs(b).max())))
            assert np.abs(a[rows] - b).max() <= tol, name
    assert np.abs(runs[0][1][3:] - runs[1][1][3:]).max() > 0       # the queries' own poses move
    scene = rt.encode([np.rint(r.transpose(1, 2, 0) * 255).astype(np.uint8) for r in refs])
    maps, poses, focal = runs[1]
    with_queries = Scene(maps[:3], poses[:3].astype(np.float64), focal.astype(np.float64), scene.K,
                         scene.image_size, scene.model_id, reference_images=scene.reference_images,
                         image_index=scene.image_index)
    a = rt.render(scene, _pose(), height=6, width=6, depth=True)
    b = rt.render(with_queries, _pose(), height=6, width=6, depth=True)
    tol = f32_tol(encoder_terms(config, 5) + renderer_terms(config, 3), max(1.0, rt.far))
    assert np.abs(a.image_float - b.image_float).max() <= tol
    assert np.abs(a.depth - b.depth).max() <= tol


def test_encode_fits_any_size(rt):
    """Images of any size go through fit_to_model (centre crop + resize); same scene as fitting
    them first. Paths and PIL images work too."""
    from PIL import Image
    H, W = rt.image_size
    odd = _images(2, (90, 70), seed=3)
    fitted = [fit_to_model(a, H, W)[0] for a in odd]
    a, b = rt.encode(odd), rt.encode([Image.fromarray(odd[0]), fitted[1]])
    np.testing.assert_array_equal(a.field_maps, b.field_maps)
    np.testing.assert_array_equal(a.world_from_cam, b.world_from_cam)


def test_render_outputs(rt, scene):
    image = rt.render(scene, _pose(), height=10, width=14)
    assert image.dtype == np.uint8 and image.shape == (10, 14, 3)
    res = rt.render(scene, _pose(), height=10, width=14, depth=True)
    assert isinstance(res, RenderResult)
    np.testing.assert_array_equal(res.image, image)
    assert res.image_float.dtype == np.float32 and res.depth.dtype == np.float32
    np.testing.assert_array_equal(res.image, np.rint(res.image_float * 255).astype(np.uint8))
    seen = res.depth > 0
    assert seen.any()
    # depth = sum(weights * z) with weights summing to 1 up to the renderer's rounding.
    tol = render_tol(rt.manifest.config, scene.num_views, rt.far)
    assert np.all((res.depth[seen] >= rt.near - tol) & (res.depth[seen] <= rt.far + tol))
    assert {"rays", "renderer", "total"} <= set(res.timings)
    # Only a height: the model's aspect ratio is kept.
    H, W = rt.image_size
    assert rt.render(scene, 0, height=8).shape == (8, round(8 * W / H), 3)


def test_render_from_images_and_int_pose(rt, scene):
    """One-shot render(images, ...) equals encode + render; pose=i is view i's predicted pose."""
    images = _images(3, rt.image_size)
    one_shot = rt.render(images, 1, height=8, width=8, depth=True)
    assert {"load", "encode"} <= set(one_shot.timings)
    cached = rt.render(scene, scene.world_from_cam[1], height=8, width=8, depth=True)
    # The same encoder and renderer calls on the same inputs in one process (threads=1): the
    # same float32 operations in the same order, equal bit for bit as the explicit-colour twin
    # (test_rgb_chunking_culling_and_workers_are_exact) asserts; the former literal atol=1e-6
    # was neither that nor a float32 rounding bound. A wrong pose or scene moves pixels by ~1e-2.
    np.testing.assert_array_equal(one_shot.image_float, cached.image_float)


def test_intrinsics_override(rt, scene):
    K = scene.intrinsics(12, 12)
    a = rt.render(scene, _pose(), height=12, width=12, depth=True)
    b = rt.render(scene, _pose(), height=12, width=12, intrinsics=K, depth=True)
    np.testing.assert_array_equal(a.image_float, b.image_float)
    K2 = K.copy()
    K2[0, 0] *= 2
    c = rt.render(scene, _pose(), height=12, width=12, intrinsics=K2, depth=True)
    assert np.abs(c.image_float - a.image_float).max() > 1e-4


def test_chunking_and_culling_invariance(model_dir, scene):
    """Chunk size and culling change only float rounding, also with empty rays: the renderer's
    (tests/tolerances.py ``render_tol``, 1.6e-5 for the tiny config; measured <= 1e-6 here).
    A sample, view or ray packed into the wrong call moves pixels by ~1e-2."""
    culled = IrisRuntime(model_dir, threads=1)
    tol = render_tol(culled.manifest.config, scene.num_views, culled.far)
    ref = culled.render(scene, SIDEWAYS, height=12, width=16, depth=True)
    assert (ref.depth == 0).any() and (ref.depth > 0).any()      # partial overlap: empty rays too
    for chunk in (7, 50):
        res = culled.render(scene, SIDEWAYS, height=12, width=16, depth=True, chunk_rays=chunk)
        assert np.abs(res.image_float - ref.image_float).max() <= tol
        assert np.abs(res.depth - ref.depth).max() <= tol
    full = IrisRuntime(model_dir, threads=1, cull=False).render(
        scene, SIDEWAYS, height=12, width=16, depth=True, chunk_rays=64)
    assert np.abs(full.image_float - ref.image_float).max() <= tol
    assert np.abs(full.depth - ref.depth).max() <= tol


# ----------------------------------------------------------------------------------------------
# Explicit colour: the reference photos sampled in numpy at the samples' projections
# ----------------------------------------------------------------------------------------------

@pytest.fixture(scope="session")
def rgb_rt(rgb_model_dir) -> IrisRuntime:
    return IrisRuntime(rgb_model_dir, threads=1)


@pytest.fixture(scope="session")
def rgb_scene(rgb_rt) -> Scene:
    return rgb_rt.encode(_images(3, rgb_rt.image_size, seed=2))


def test_rgb_model_is_recognised(rgb_rt, rt):
    assert rgb_rt.manifest.explicit_rgb is True and rt.manifest.explicit_rgb is False
    assert "colours" in rgb_rt.manifest.graphs["renderer"].inputs
    assert "colours" not in rt.manifest.graphs["renderer"].inputs


def test_rgb_chunking_culling_and_workers_are_exact(rgb_model_dir, rgb_rt, rgb_scene):
    """The colours follow the packing of every call: chunk sizes, culling off and 2 workers
    change only float rounding (the renderer's, tests/tolerances.py ``render_tol``; measured
    <= 1e-6 here), and a one-shot render from the images is the same render, bit for bit."""
    ref = rgb_rt.render(rgb_scene, SIDEWAYS, height=12, width=16, depth=True)
    assert (ref.depth == 0).any() and (ref.depth > 0).any()
    others = [rgb_rt.render(rgb_scene, SIDEWAYS, height=12, width=16, depth=True, chunk_rays=c)
              for c in (7, 50)]
    others.append(IrisRuntime(rgb_model_dir, threads=1, cull=False).render(
        rgb_scene, SIDEWAYS, height=12, width=16, depth=True, chunk_rays=64))
    others.append(IrisRuntime(rgb_model_dir, threads=2, workers=2).render(
        rgb_scene, SIDEWAYS, height=12, width=16, depth=True, chunk_rays=40))
    tol = render_tol(rgb_rt.manifest.config, rgb_scene.num_views, rgb_rt.far)
    for res in others:
        assert np.abs(res.image_float - ref.image_float).max() <= tol
        assert np.abs(res.depth - ref.depth).max() <= tol
    one_shot = rgb_rt.render(_images(3, rgb_rt.image_size, seed=2), SIDEWAYS, height=12,
                             width=16, depth=True)
    np.testing.assert_array_equal(one_shot.image_float, ref.image_float)


def test_rgb_render_reads_each_views_photo(rgb_rt, rgb_scene):
    """The runtime feeds each view's photo (``reference_images[image_index]``): other photos
    behind the same field maps change the render; a subset keeps the index in step with its
    views, and a hand-built Scene with the subset's photos renders the same."""
    pose = _pose()
    base = rgb_rt.render(rgb_scene, pose, height=8, width=8, depth=True)
    swapped = dataclasses.replace(rgb_scene, reference_images=1.0 - rgb_scene.reference_images)
    assert np.abs(rgb_rt.render(swapped, pose, height=8, width=8, depth=True).image_float
                  - base.image_float).max() > 1e-3
    np.testing.assert_array_equal(rgb_scene.image_index, [0, 1, 2])
    sub = rgb_scene.subset([2, 0])
    np.testing.assert_array_equal(sub.image_index, [2, 0])
    np.testing.assert_array_equal(sub.subset([1]).image_index, [0])
    a = rgb_rt.render(sub, pose, height=8, width=8, depth=True)
    by_hand = Scene(sub.field_maps, sub.world_from_cam, sub.focal, sub.K, sub.image_size,
                    sub.model_id, rgb_scene.reference_images[[2, 0]])       # default index 0, 1
    b = rgb_rt.render(by_hand, pose, height=8, width=8, depth=True)
    np.testing.assert_array_equal(a.image_float, b.image_float)
    indexed = Scene(sub.field_maps, sub.world_from_cam, sub.focal, sub.K, sub.image_size,
                    sub.model_id, rgb_scene.reference_images, [2, 0])
    np.testing.assert_array_equal(rgb_rt.render(indexed, pose, height=8, width=8, depth=True)
                                  .image_float, a.image_float)


def test_rgb_scene_without_its_photos_is_a_typed_error(rgb_rt, rgb_scene, rt, tmp_path):
    """An explicit-colour render needs each view's photo: a Scene without reference_images, or
    with a different number of them and no image_index, is refused (InputError naming them);
    a missing or unreadable photo path is an ImageError naming it. A model without explicit
    colour renders such Scenes as before."""
    bare = Scene(rgb_scene.field_maps, rgb_scene.world_from_cam, rgb_scene.focal, rgb_scene.K,
                 rgb_scene.image_size, rgb_scene.model_id)
    assert bare.image_index is None
    with pytest.raises(InputError, match="reference_images") as info:
        rgb_rt.render(bare, 0, height=4, width=4)
    assert isinstance(info.value, ValueError) and "explicit colour" in str(info.value)
    unknown = Scene(rgb_scene.field_maps[:2], rgb_scene.world_from_cam[:2], rgb_scene.focal,
                    rgb_scene.K, rgb_scene.image_size, rgb_scene.model_id,
                    rgb_scene.reference_images)                            # 3 photos, 2 views
    assert unknown.image_index is None
    with pytest.raises(InputError, match="image_index"):
        rgb_rt.render(unknown, 0, height=4, width=4)
    plain = rt.encode(_images(2, rt.image_size))
    rt.render(Scene(plain.field_maps, plain.world_from_cam, plain.focal, plain.K,
                    plain.image_size, plain.model_id), 0, height=4, width=4)
    missing = tmp_path / "missing.png"
    (tmp_path / "broken.png").write_bytes(b"not a png")
    for bad in (missing, tmp_path / "broken.png"):
        with pytest.raises(ImageError, match=bad.name) as info:
            rgb_rt.render([_images(1, rgb_rt.image_size)[0], bad], 0, height=4, width=4)
        assert isinstance(info.value, IrisError)
    for index, match in (([0, 3], "image_index"), ([0], "image_index"), ([0.0, 1.0], "image_index")):
        with pytest.raises(InputError, match=match):
            Scene(rgb_scene.field_maps[:2], rgb_scene.world_from_cam[:2], rgb_scene.focal,
                  rgb_scene.K, rgb_scene.image_size, "", rgb_scene.reference_images, index)
    with pytest.raises(InputError, match="without reference_images"):
        Scene(rgb_scene.field_maps, rgb_scene.world_from_cam, rgb_scene.focal, rgb_scene.K,
              rgb_scene.image_size, "", None, [0, 1, 2])


def test_progress_callback(rt, scene):
    calls = []
    rt.render(scene, 0, height=6, width=6, chunk_rays=10,
              progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (36, 36) and [d for d, _ in calls] == sorted(d for d, _ in calls)


def test_threads_render_like_serial(model_dir, scene, monkeypatch):
    """4 threads on a fresh runtime (racing to create the sessions) == serial results."""
    runtime = IrisRuntime(model_dir, threads=1)
    created = []
    original = IrisRuntime._create_session
    monkeypatch.setattr(IrisRuntime, "_create_session",
                        lambda self, name: created.append(name) or original(self, name))
    poses = [_pose(angle=a) for a in (0.0, 0.03, -0.04, 0.05)]
    results, errors = [None] * 4, []
    barrier = threading.Barrier(4)

    def work(i):
        try:
            barrier.wait()
            results[i] = runtime.render(scene, poses[i], height=8, width=8, depth=True)
        except Exception as exc:      # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert sorted(created) == ["renderer"]         # created once despite the race
    for i, pose in enumerate(poses):
        serial = runtime.render(scene, pose, height=8, width=8, depth=True)
        np.testing.assert_array_equal(results[i].image_float, serial.image_float)
        np.testing.assert_array_equal(results[i].depth, serial.depth)


# ----------------------------------------------------------------------------------------------
# Bad input -> typed errors
# ----------------------------------------------------------------------------------------------

def _mirrored():
    T = np.eye(4)
    T[2, 2] = -1
    return T


@pytest.mark.parametrize("pose, match", [
    (np.eye(3), "shape"),
    (np.full((4, 4), np.nan), "NaN"),
    (np.diag([2.0, 2.0, 2.0, 1.0]), "orthonormal"),
    (_mirrored(), "mirrored"),
    (np.diag([0.0, 0.0, 0.0, 1.0]), "singular"),
    (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], float), "last row"),
    ("eye", "4x4"),
    (3, "out of range"),
    (-1, "out of range"),
    (True, "4x4"),
])
def test_bad_pose(rt, scene, pose, match):
    with pytest.raises(InputError, match=match) as info:
        rt.render(scene, pose, height=4, width=4)
    assert "pose" in str(info.value)
    assert isinstance(info.value, ValueError) and isinstance(info.value, IrisError)


@pytest.mark.parametrize("images, error, match", [
    ([], InputError, "at least one"),
    (np.zeros((64, 64, 3), np.uint8), InputError, "wrap it in a list"),
    ("photo.png", InputError, "wrap it in a list"),
    ([np.zeros((64, 64, 5), np.uint8)], ImageError, r"images\[0\]"),
    ([np.zeros((64, 64, 3), np.int64)], ImageError, "dtype"),
    ([np.full((8, 8, 3), np.nan, np.float32)], ImageError, "NaN"),
    ([np.zeros((64, 64, 3), np.uint8), "/nonexistent/x.png"], ImageError, "no such file"),
    (42, InputError, "sequence"),
])
def test_bad_images(rt, images, error, match):
    with pytest.raises(error, match=match):
        rt.encode(images)


@pytest.mark.parametrize("kwargs, match", [
    ({"height": 0}, "height"), ({"width": 2.5}, "width"), ({"chunk_rays": 0}, "chunk_rays"),
    ({"intrinsics": np.eye(4)}, "intrinsics"), ({"intrinsics": -np.eye(3)}, "intrinsics"),
])
def test_bad_render_arguments(rt, scene, kwargs, match):
    with pytest.raises(InputError, match=match):
        rt.render(scene, 0, **kwargs)


def test_bad_runtime_arguments(model_dir):
    with pytest.raises(InputError, match="threads"):
        IrisRuntime(model_dir, threads=0)
    with pytest.raises(InputError, match="precision"):
        IrisRuntime(model_dir, precision="fp16")


def test_scene_of_another_model(rt, scene):
    other = dataclasses.replace(scene, model_id="0" * 64)
    with pytest.raises(InputError, match="another model"):
        rt.render(other, 0, height=4, width=4)


# ----------------------------------------------------------------------------------------------
# Model files and manifest
# ----------------------------------------------------------------------------------------------

@pytest.fixture
def model_copy(model_dir, tmp_path) -> Path:
    out = tmp_path / "model"
    shutil.copytree(model_dir, out)
    return out


def _edit_manifest(d: Path, edit) -> None:
    doc = json.loads((d / "iris.json").read_text())
    edit(doc)
    (d / "iris.json").write_text(json.dumps(doc))


def test_tampered_graph(model_copy):
    data = bytearray((model_copy / "renderer.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (model_copy / "renderer.onnx").write_bytes(bytes(data))
    with pytest.raises(ModelIntegrityError, match="sha256") as info:
        IrisRuntime(model_copy)
    assert isinstance(info.value, ModelFileError) and isinstance(info.value, OSError)


def test_graph_replaced_after_check(model_copy):
    """The session is built from the bytes it hashes: a swap after construction is caught."""
    runtime = IrisRuntime(model_copy, threads=1)
    shutil.copy(model_copy / "renderer.onnx", model_copy / "encoder.onnx")
    with pytest.raises(ModelIntegrityError, match="encoder"):
        runtime.encode(_images(1, runtime.image_size))


@pytest.mark.parametrize("edit, error, match", [
    (lambda d: d.update(io_spec_version=2), ModelFormatError, "re-export with iris-export"),
    (lambda d: d["graphs"]["renderer"]["inputs"].pop("colours"), ManifestError, "colours"),
    (lambda d: d["graphs"]["renderer_int8"]["inputs"].pop("colours"), ManifestError, "colours"),
    (lambda d: d["config"].update(explicit_rgb="yes"), ManifestError, "explicit_rgb"),
    # (blend_angle, which weights the explicit colour, set to the plain mean with it)
    (lambda d: d["config"].update(explicit_rgb=False, blend_angle=0.0), ManifestError, "colours"),
    (lambda d: d["config"].update(explicit_rgb=False, blend_angle=0.5), ManifestError,
     "blend_angle"),
])
def test_bad_rgb_manifest(rgb_model_dir, tmp_path, edit, error, match):
    """An explicit-colour manifest must say so consistently (config and the renderers' inputs)
    under I/O spec 3."""
    model_copy = tmp_path / "model"
    shutil.copytree(rgb_model_dir, model_copy)
    _edit_manifest(model_copy, edit)
    with pytest.raises(error, match=match):
        IrisRuntime(model_copy)


@pytest.mark.parametrize("version", [2, 3])
def test_io_spec_with_a_bool_mask_is_refused_with_a_re_export_hint(model_copy, version):
    """I/O spec 2 and 3 renderers take a bool ``mask``; this runtime feeds validity weights
    (float32): such a manifest is refused up front, naming the fix, not at the first render."""
    _edit_manifest(model_copy, lambda d: d.update(io_spec_version=version))
    with pytest.raises(ModelFormatError, match="bool mask.*re-export with iris-export"):
        IrisRuntime(model_copy)


@pytest.mark.parametrize("edit, error, match", [
    (lambda d: d.update(version=1), ModelFormatError, "re-export with iris-export"),
    (lambda d: d.update(version=3), ModelFormatError, "version 2"),
    (lambda d: d.update(format="something-else"), ModelFormatError, "iris-model"),
    (lambda d: d.update(io_spec_version=7), ModelFormatError, "I/O spec"),
    (lambda d: d.update(io_spec_version=1), ModelFormatError, "I/O spec"),
    (lambda d: d.update(io_spec_version=True), ModelFormatError, "I/O spec"),
    (lambda d: d["graphs"]["renderer"].update(file="../renderer.onnx"), ManifestError, r"'\.\.'"),
    (lambda d: d["graphs"]["renderer"].update(file="/etc/passwd"), ManifestError, "relative"),
    (lambda d: d["graphs"]["encoder"].update(file="sub/../../x.onnx"), ManifestError, r"'\.\.'"),
    (lambda d: d["graphs"]["renderer"]["inputs"].pop("mask"), ManifestError, "mask"),
    (lambda d: d["graphs"].pop("encoder"), ManifestError, "encoder"),
    (lambda d: d["graphs"]["renderer"].update(sha256="xyz"), ManifestError, "sha256"),
    (lambda d: d.update(near=2.0), ManifestError, "near"),
    (lambda d: d.update(median_depth=d["far"] + 1), ManifestError, "median_depth"),
    (lambda d: d.update(median_depth="0.5"), ManifestError, "median_depth"),
])
def test_bad_manifest(model_copy, edit, error, match):
    _edit_manifest(model_copy, edit)
    with pytest.raises(error, match=match):
        IrisRuntime(model_copy)


def test_median_depth_sets_the_cameras_unit_only(model_copy):
    """The manifest's optional ``median_depth`` moves the solve's ``depth_range`` (the cameras'
    unit: its DEPTH_TARGET point is ``median_depth``), never the sampled [near, far]; absent,
    the unit range is [near, far] itself (every model exported before it)."""
    from iris_runtime.cameras import DEPTH_TARGET
    doc = json.loads((model_copy / "iris.json").read_text())
    near, far = doc["near"], doc["far"]
    _edit_manifest(model_copy, lambda d: d.pop("median_depth", None))
    assert IrisRuntime(model_copy).unit_range == (near, far)
    median = near + 0.25 * (far - near)
    _edit_manifest(model_copy, lambda d: d.update(median_depth=median))
    rt = IrisRuntime(model_copy)
    lo, hi = rt.unit_range
    assert (rt.near, rt.far) == (near, far) and lo == near
    assert lo + DEPTH_TARGET * (hi - lo) == pytest.approx(median, abs=1e-12)


def test_symlink_escaping_model_dir(model_copy, tmp_path):
    outside = tmp_path / "outside.onnx"
    shutil.copy(model_copy / "renderer.onnx", outside)
    (model_copy / "link.onnx").symlink_to(outside)
    _edit_manifest(model_copy, lambda d: d["graphs"]["renderer"].update(file="link.onnx"))
    with pytest.raises(ManifestError, match="outside the model directory"):
        IrisRuntime(model_copy)


def test_missing_files(model_copy, tmp_path):
    with pytest.raises(ModelFileError, match="no such directory"):
        IrisRuntime(tmp_path / "nope")
    (model_copy / "renderer.onnx").unlink()
    with pytest.raises(ModelFileError, match="missing"):
        IrisRuntime(model_copy)
    (model_copy / "iris.json").write_text("{not json")
    with pytest.raises(ManifestError, match="JSON"):
        IrisRuntime(model_copy)
    (model_copy / "iris.json").unlink()
    with pytest.raises(ManifestError, match="iris.json"):
        IrisRuntime(model_copy)


def test_int8_needs_quantised_export(model_dir):
    doc = json.loads((Path(model_dir) / "iris.json").read_text())
    if "renderer_int8" in doc["graphs"]:
        pytest.skip("this model has an int8 renderer")
    with pytest.raises(ManifestError, match="int8"):
        IrisRuntime(model_dir, precision="int8")


def test_int8_variant_is_used(model_copy, scene):
    """precision="int8" runs graphs.renderer_int8 (here: a stand-in pointing at the float graph,
    so the result must be the float one; a real int8 export differs by ~1e-3)."""
    _edit_manifest(model_copy, lambda d: d["graphs"].update(
        renderer_int8=dict(d["graphs"]["renderer"], file="renderer.int8.onnx",
                           variant_of="renderer", precision="int8")))
    shutil.copy(model_copy / "renderer.onnx", model_copy / "renderer.int8.onnx")
    runtime = IrisRuntime(model_copy, threads=1, precision="int8")
    float_runtime = IrisRuntime(model_copy, threads=1)
    a = runtime.render(scene, 1, height=6, width=6, depth=True)
    b = float_runtime.render(scene, 1, height=6, width=6, depth=True)
    np.testing.assert_array_equal(a.image_float, b.image_float)
    assert set(runtime._sessions) == {"renderer_int8"}


# ----------------------------------------------------------------------------------------------
# Orbit path
# ----------------------------------------------------------------------------------------------

def test_orbit_is_closed_smooth_and_looks_at_the_scene():
    from iris_runtime.orbit import look_at, scene_centre
    angles = np.linspace(0, 2 * np.pi, 5, endpoint=False)
    ring = np.stack([look_at(np.array([2 * np.cos(t), 0.3, 2 * np.sin(t)]), np.zeros(3),
                             np.array([0.0, 1.0, 0.0])) for t in angles])
    for cams, far in ((ring, 5.0), (np.stack([np.eye(4), _pose(), _pose(angle=-0.1)]), 1.0),
                      (np.eye(4)[None], 1.0)):
        path = orbit_poses(cams, 24, near=0.1, far=far)
        assert path.shape == (24, 4, 4) and all(G.is_rigid(T) for T in path)
        target = scene_centre(cams, 0.1, far)
        to_target = target - path[:, :3, 3]
        to_target /= np.linalg.norm(to_target, axis=1, keepdims=True)
        np.testing.assert_allclose((to_target * path[:, :3, 2]).sum(1), 1.0, atol=1e-9)
        steps = np.linalg.norm(np.diff(path[:, :3, 3], axis=0, append=path[:1, :3, 3]), axis=1)
        assert steps.max() < 1.5 * steps.min() + 1e-12        # closed, no jump back to the start
    # The ring's path goes through its cameras.
    path = orbit_poses(ring, 360, near=0.1, far=5.0)
    dist = np.linalg.norm(path[:, None, :3, 3] - ring[None, :, :3, 3], axis=-1).min(0)
    assert dist.max() < 0.05


def test_look_at_with_roll_is_the_synthetic_cameras_rule():
    """``orbit.look_at`` with ``roll`` is the one look-at of the project: the synthetic data's
    cameras (z-up world, ``roll`` about the optical axis) are ``look_at(eye, target, down=-z,
    roll=roll)``, equal value for value to that rule written out."""
    from iris_runtime.orbit import look_at

    def by_hand(eye, target, roll):
        z = (target - eye) / np.linalg.norm(target - eye)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        c, s = np.cos(roll), np.sin(roll)
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = c * x + s * y, -s * x + c * y, z, eye
        return T

    rng = np.random.default_rng(4)
    for _ in range(200):
        eye, target = rng.normal(size=3), rng.normal(0, 0.1, size=3)
        roll = float(rng.normal(0, 0.03)) if rng.random() < 0.8 else 0.0
        T = look_at(eye, target, np.array([0.0, 0.0, -1.0]), roll=roll)
        np.testing.assert_array_equal(T, by_hand(eye, target, roll))
        assert G.is_rigid(T)


# ----------------------------------------------------------------------------------------------
# Packaging and CLI (subprocesses with torch blocked)
# ----------------------------------------------------------------------------------------------

_NO_TORCH = "import sys; sys.modules['torch'] = None; "


def _python(code: str, *args, cwd=None):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-c", _NO_TORCH + code, *map(str, args)], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=300)


def test_import_and_render_without_torch(model_dir):
    code = ("import numpy as np, iris_runtime, iris_runtime.cli, iris_runtime.orbit; "
            "rt = iris_runtime.IrisRuntime(sys.argv[1], threads=1); "
            "s = rt.encode([np.zeros((64, 64, 3), np.uint8)] * 2); "
            "assert rt.render(s, 1, height=4, width=4).shape == (4, 4, 3); "
            "bad = [m for m in sys.modules if m.split('.')[0] in ('torch', 'iris_train', 'export') "
            "and sys.modules[m] is not None]; "
            "assert not bad, bad; print('ok')")
    proc = _python(code, model_dir)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().endswith("ok")


def test_cli_end_to_end(model_dir, tmp_path):
    import cv2
    from PIL import Image
    paths = []
    for i, size in enumerate([(80, 100), (64, 64)]):
        paths.append(tmp_path / f"in{i}.png")
        Image.fromarray(_images(1, size, seed=i)[0]).save(paths[-1])
    pose_file = tmp_path / "poses.json"
    pose_file.write_text(json.dumps([_pose().tolist(), np.eye(4).tolist()]))
    out = tmp_path / "out"
    code = "from iris_runtime.cli import main; sys.exit(main(sys.argv[1:]))"
    proc = _python(code, model_dir, *paths, "-o", out, "--view", 1, "--pose", pose_file,
                   "--orbit", 3, "--size", "8x12", "--threads", 1)
    assert proc.returncode == 0, proc.stderr
    assert "transforms.json" in proc.stdout and "renderer" in proc.stdout
    for name in ("view_001", "pose_000", "pose_001", "orbit_0000", "orbit_0002"):
        assert Image.open(out / f"{name}.png").size == (12, 8)
        depth16 = cv2.imread(str(out / f"{name}_depth.png"), cv2.IMREAD_UNCHANGED)
        assert depth16.dtype == np.uint16 and depth16.shape == (8, 12)
        depth = np.load(out / f"{name}_depth.npy")
        np.testing.assert_allclose(depth16, np.rint(np.clip(depth, 0, 1) * 65535), atol=1)
    assert (out / "orbit.mp4").stat().st_size > 0
    assert len(json.loads((out / "orbit_poses.json").read_text())) == 3
    doc = json.loads((out / "transforms.json").read_text())
    assert [f["file_path"] for f in doc["frames"]] == ["inputs/000.png", "inputs/001.png"]
    assert all((out / f["file_path"]).is_file() for f in doc["frames"])
    assert (out / "colmap" / "images.txt").is_file() and (out / "colmap" / "cameras.txt").is_file()

    # Errors: one line on stderr, exit code 2, no traceback, nothing written.
    (tmp_path / "bad.json").write_text(json.dumps(np.diag([1.0, 1.0, -1.0, 1.0]).tolist()))
    for args in ([model_dir, paths[0], "-o", tmp_path / "o2", "--pose", tmp_path / "bad.json"],
                 [tmp_path / "nomodel", paths[0], "-o", tmp_path / "o2"],
                 [model_dir, tmp_path / "missing.png", "-o", tmp_path / "o2"],
                 [model_dir, paths[0], "-o", tmp_path / "o2", "--view", 4],
                 [model_dir, paths[0], "-o", tmp_path / "o2", "--size", "big"]):
        proc = _python(code, *args)
        assert proc.returncode == 2, proc.stderr
        assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
        assert not (tmp_path / "o2").exists()


def test_cli_locate(model_dir, tmp_path):
    """iris-render --locate: poses printed and written to located_poses.json (usable with --pose),
    located views rendered; the same numbers as IrisRuntime.locate."""
    from PIL import Image
    paths = []
    for i in range(4):
        paths.append(tmp_path / f"in{i}.png")
        Image.fromarray(_images(1, (64, 64), seed=20 + i)[0]).save(paths[-1])
    out = tmp_path / "out"
    code = "from iris_runtime.cli import main; sys.exit(main(sys.argv[1:]))"
    proc = _python(code, model_dir, *paths[:2], "-o", out, "--size", "4x4", "--threads", 1,
                   "--locate", paths[2], paths[3], "--no-depth")
    assert proc.returncode == 0, proc.stderr
    located = np.asarray(json.loads((out / "located_poses.json").read_text()))
    assert located.shape == (2, 4, 4) and all(G.is_rigid(T) for T in located)
    runtime = IrisRuntime(model_dir, threads=1)
    np.testing.assert_allclose(located, runtime.locate(runtime.encode(paths[:2]), paths[2:]),
                               atol=1e-12, rtol=0)
    assert str(paths[2]) in proc.stdout and "located_poses.json" in proc.stdout
    assert sorted(p.name for p in out.glob("located_*.png")) == ["located_000.png", "located_001.png"]
    assert not list(out.glob("view_*.png"))            # --locate is a target: no default views
    proc = _python(code, model_dir, paths[0], "-o", tmp_path / "o2", "--locate",
                   tmp_path / "missing.png")
    assert proc.returncode == 2 and "missing.png" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "o2").exists()


# ----------------------------------------------------------------------------------------------
# Parity on the shipped, trained model and the committed held-out sample scene
# ----------------------------------------------------------------------------------------------

SAMPLE = REPO / "samples" / "heldout-1000003"


@pytest.fixture(scope="session")
def shipped_pair(shipped_export):
    """(runtime, runtime scene, IrisModel, torch scene) for the trained default model (its export:
    conftest ``shipped_export``)."""
    out, model = shipped_export
    runtime = IrisRuntime(out, threads=1)
    # The shipped renderer was trained on solved cameras and its head distilled from the solve:
    # its export's default refines the head's cameras into the solve's terms.
    assert runtime.default_cameras == "refined"
    paths = sorted(SAMPLE.glob("frame_*.png"))
    scene = runtime.encode(paths, cameras="model")     # the graphs against torch: the head's cameras
    from iris_runtime.images import load_image
    return runtime, scene, model, _torch_scene(model, [load_image(p) for p in paths])


@pytest.mark.torch
def test_trained_model_runtime_matches_torch(shipped_pair):
    """The encoder against torch float32; the renders, end to end (each side its own scene and
    target pose), against torch in float64: within 1e-5 plus twice what float32 torch itself is
    from float64. The render is continuous but not flat in the cameras (validity fades over
    EDGE_FADE pixels outside each image): where a ray's last samples fade out near a reference
    camera, float32 rounding of the cameras moves a pixel by more than 1e-5 in torch too (this
    sample is held-out scene 1000003, the ill-conditioned one of ``benchmarks/pose_sensitivity.py``:
    torch float32 there is 7.4e-5 from float64).

    The renders are 32 x 32 (the model's aspect, so the same intrinsics path as its 64 x 64:
    ``Scene.intrinsics``): a ray's colour does not depend on how many others are rendered, and
    a quarter of the rays, spread over the whole frame, are checked at a quarter of the cost
    (torch float64 takes ~40 s of one core per 64 x 64 render, and each target needs two)."""
    import copy
    import dataclasses

    import torch
    runtime, scene, model, tscene = shipped_pair
    size = (32, 32)
    assert np.abs(scene.world_from_cam - tscene.world_from_cam.double().numpy()).max() <= 1e-5
    assert np.abs(scene.focal - tscene.focal.double().numpy()).max() <= 1e-5
    model64 = copy.deepcopy(model).double()
    from iris_runtime.images import load_image
    x = np.stack([load_image(p) for p in sorted(SAMPLE.glob("frame_*.png"))]).astype(np.float32)
    x = torch.from_numpy(x.transpose(0, 3, 1, 2) * np.float32(1.0 / 255.0))
    with torch.no_grad():
        t64, t32 = model64.encode(x.double()), model.encode(x)
    refs = [0, 2, 3, 5, 7]
    for target in (1, 4, 6):
        res = runtime.render(scene.subset(refs), scene.world_from_cam[target], height=size[0],
                             width=size[1], depth=True)
        with torch.no_grad():
            rgb, depth = model64.render(t64.subset(refs), t64.world_from_cam[[target]], *size)
            rgb32, _ = model.render(t32.subset(refs), t32.world_from_cam[[target]], *size)
            # The same float64 render from the runtime's cameras: how much the cameras' float32
            # difference moves this ill-conditioned scene (a slope of the validity fade near a
            # reference camera), measured rather than assumed from one CPU's run.
            rc = dataclasses.replace(t64, world_from_cam=torch.from_numpy(scene.world_from_cam),
                                     focal=torch.from_numpy(scene.focal))
            rgb_rc, _ = model64.render(rc.subset(refs), rc.world_from_cam[[target]], *size)
        float32_err = np.abs(rgb32[0].double().numpy() - rgb[0].numpy()).max()
        camera_err = np.abs(rgb_rc[0].numpy() - rgb[0].numpy()).max()
        assert np.abs(res.image_float - rgb[0].numpy()).max() <= (1e-5 + 2 * float32_err
                                                                  + 2 * camera_err)
        assert np.abs(res.depth - depth[0].numpy()).max() <= 1e-4


@pytest.mark.torch
def test_trained_model_locate_matches_torch(shipped_pair):
    """The shipped model: the targets of the sample scene located from its references by the
    encoder (the head's cameras), runtime vs torch."""
    import torch
    runtime, _, model, _ = shipped_pair
    paths = sorted(SAMPLE.glob("frame_*.png"))
    refs, targets = [paths[i] for i in (0, 2, 3, 5, 7)], [paths[i] for i in (1, 4, 6)]
    scene = runtime.encode(refs, cameras="model")
    got = runtime.locate(scene, targets)
    with torch.no_grad():
        want = model.locate(torch.from_numpy(scene.reference_images.copy()),
                            torch.from_numpy(runtime._load_images(targets)))
    assert np.abs(got - want.double().numpy()).max() <= 1e-5


@pytest.mark.torch
def test_trained_model_cameras_graph_is_the_encoders_camera_half(shipped_pair):
    """The shipped model's camera head reads an encoder of its own, so its export has the
    "encoder_cameras" graph, validated against torch like the encoder. Its cameras equal the
    encoder graph's bit for bit (all references, and references with queries), and the runtime
    runs it, not the whole encoder, where it needs no field maps: the refinement's start in the
    photos' canonical order, and ``locate``."""
    import torch

    from iris_runtime.cameras import canonical_order
    runtime, _, model, _ = shipped_pair
    assert "encoder_cameras" in runtime.manifest.graphs
    validation = json.loads((runtime.manifest.model_dir / "iris.json").read_text())["validation"]
    assert validation["encoder_cameras"]["passed"]
    paths = sorted(SAMPLE.glob("frame_*.png"))
    batch = runtime._load_images(paths)
    for is_reference in (np.ones(8, bool), np.arange(8) < 5):
        cams = runtime._run_cameras(batch, is_reference)
        full = runtime._run_encoder(batch, is_reference)[1:]
        for a, b in zip(cams, full):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="camera_encoder"):
        from .conftest import random_model
        random_model("tiny").camera_stages(torch.zeros(1, 2, 3, 64, 64), None)

    runs = []
    session = runtime._session

    def counted(name):
        s = session(name)

        class Counting:
            def run(self, outputs, feed):
                runs.append((name, len(feed["images"])))
                return s.run(outputs, feed)
        return Counting()

    runtime._session = counted
    try:
        photos = [paths[i] for i in (3, 0, 5, 1, 7, 2, 6, 4)]
        from iris_runtime.images import load_image
        assert not np.array_equal(canonical_order([load_image(p) for p in photos]), np.arange(8))
        scene = runtime.encode(photos, cameras="refined")
        assert [name for name, _ in runs] == ["encoder", "encoder_cameras"]
        runs.clear()
        runtime.locate(scene, paths[0])
        assert runs == [("encoder_cameras", 9)]
    finally:
        del runtime._session

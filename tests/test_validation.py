"""iris_runtime.validation: the one check per kind of public input, at its documented tolerance."""
from __future__ import annotations

import json

import numpy as np
import pytest

from iris_runtime import geometry as G
from iris_runtime.errors import ImageError, InputError, IrisError
from iris_runtime.validation import (FLOAT_IMAGE_ATOL, INTRINSICS_ATOL, RIGID_ATOL, SNAP_ATOL,
                                     check_images, check_integer, check_intrinsics,
                                     check_world_from_cam, rigidity_error, snap_world_from_cam)


def _pose(angle=0.7, t=(1.0, -2.0, 0.5)) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


def _scaled(err: float) -> np.ndarray:
    """A pose whose rotation's first column is scaled so that max |R^T R - I| = err (and
    |det R - 1| ~ err / 2)."""
    T = _pose()
    T[:3, 0] *= np.sqrt(1 + err)
    return T


# -- world_from_cam ------------------------------------------------------------------------------

def test_rigid_tolerance_is_one_constant_at_the_boundary():
    assert RIGID_ATOL == 1e-4 and SNAP_ATOL == 1e-3
    ok, bad = _scaled(0.9 * RIGID_ATOL), _scaled(1.1 * RIGID_ATOL)
    out = check_world_from_cam(ok)
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, ok)                       # never changed
    assert G.is_rigid(ok) and not G.is_rigid(bad)                # is_rigid: the same predicate
    with pytest.raises(InputError, match="not orthonormal"):
        check_world_from_cam(bad)
    f32 = _pose().astype(np.float32)
    np.testing.assert_array_equal(check_world_from_cam(f32), f32.astype(np.float64))
    assert rigidity_error(_pose()) < 1e-15


@pytest.mark.parametrize("value, match", [
    (np.eye(3), "4x4"), (np.eye(4)[None], "shape"), ("eye", "of numbers"), (None, "of numbers"),
    (np.eye(4, dtype=bool), "of numbers"), (np.eye(4, dtype=complex), "of numbers"),
    ([[1, 0, 0], [0, 1, 0, 0]], "of numbers"), (np.full((4, 4), np.nan), "NaN or inf"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "mirrored"), (np.diag([0.0, 0.0, 0.0, 1.0]), "singular"),
    (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], float), "last row"),
    (np.diag([2.0, 2.0, 2.0, 1.0]), "orthonormal"),
])
def test_world_from_cam_errors_name_the_argument_and_the_fault(value, match):
    with pytest.raises(InputError, match=match) as e:
        check_world_from_cam(value, "pose")
    assert str(e.value).startswith("pose: ")
    assert isinstance(e.value, IrisError) and isinstance(e.value, ValueError)


def test_world_from_cam_batch_names_the_view():
    T = np.stack([_pose(0.1), _pose(0.2), _pose(0.3)])
    np.testing.assert_array_equal(check_world_from_cam(T, "world_from_cam", batch=True), T)
    bad = T.copy()
    bad[2, :3, 0] *= -1
    with pytest.raises(InputError, match=r"^world_from_cam\[2\]: .*mirrored"):
        check_world_from_cam(bad, "world_from_cam", batch=True)
    bad = T.copy()
    bad[1, 0, 3] = np.inf
    with pytest.raises(InputError, match=r"^world_from_cam\[1\]: contains NaN or inf"):
        check_world_from_cam(bad, "world_from_cam", batch=True)
    for shape in ((4, 4), (0, 4, 4), (2, 3, 4)):
        with pytest.raises(InputError, match=r"shape \[V, 4, 4\]"):
            check_world_from_cam(np.zeros(shape), "world_from_cam", batch=True)


def test_snap_keeps_rigid_poses_bitwise_and_snaps_rounded_ones():
    T = _pose()
    near = _scaled(0.5 * RIGID_ATOL)
    np.testing.assert_array_equal(snap_world_from_cam(T, "m"), T)
    np.testing.assert_array_equal(snap_world_from_cam(near, "m"), near)       # as is
    rounded = np.round(_pose(0.5), 3)                                        # 3 decimals
    assert RIGID_ATOL < rigidity_error(rounded) <= SNAP_ATOL
    snapped = snap_world_from_cam(rounded, "m")
    assert rigidity_error(snapped) < 1e-12
    np.testing.assert_array_equal(snapped[:3, 3], rounded[:3, 3])
    np.testing.assert_allclose(snapped, _pose(0.5), atol=1e-3)
    with pytest.raises(InputError, match=r"^m: .*within 0\.001.*not orthonormal"):
        snap_world_from_cam(_scaled(2 * SNAP_ATOL), "m")
    with pytest.raises(InputError, match="mirrored"):
        snap_world_from_cam(np.diag([1.0, 1.0, -1.0, 1.0]), "m")


def test_cli_pose_files_use_the_reader_rule(tmp_path):
    """iris-render --pose: checked when read (before anything is written), snapped like a camera
    file; a full-precision file (orbit_poses.json) is read bit for bit."""
    from iris_runtime.render_job import _read_poses
    exact, rounded = _pose(), np.round(_pose(0.5), 3)
    (tmp_path / "p.json").write_text(json.dumps([exact.tolist(), rounded.tolist()]))
    a, b = _read_poses(str(tmp_path / "p.json"))
    np.testing.assert_array_equal(a, exact)
    assert rigidity_error(b) < 1e-12
    (tmp_path / "m.json").write_text(json.dumps(np.diag([1.0, 1.0, -1.0, 1.0]).tolist()))
    with pytest.raises(InputError, match=r"--pose .*m\.json\[0\]: .*mirrored"):
        _read_poses(str(tmp_path / "m.json"))


# -- intrinsics ----------------------------------------------------------------------------------

K = np.array([[500.0, 0.0, 320.0], [0.0, 510.0, 240.0], [0.0, 0.0, 1.0]])


def test_intrinsics_pass_unchanged_and_broadcast_per_view():
    np.testing.assert_array_equal(check_intrinsics(K), K)
    np.testing.assert_array_equal(check_intrinsics(K.astype(np.float32).tolist()), K)
    assert check_intrinsics(K, "K", views=3).shape == (3, 3, 3)
    per_view = np.stack([K, 2 * K * [[1], [1], [0.5]]])
    np.testing.assert_array_equal(check_intrinsics(per_view, "K", views=2), per_view)
    off = K.copy()
    off[1, 0] = 0.5 * INTRINSICS_ATOL                          # float64 round-off: accepted
    check_intrinsics(off)
    shifted = K.copy()
    shifted[:2, 2] = [-1000.0, 5000.0]                         # a tile: principal point anywhere
    check_intrinsics(shifted, "intrinsics", 8, 8)


@pytest.mark.parametrize("edit, match", [
    (lambda k: k.__setitem__((0, 1), 1.0), "no skew"),
    (lambda k: k.__setitem__((1, 0), 1e-6), "pinhole"),
    (lambda k: k.__setitem__((2, 2), 1.0 + 1e-6), "pinhole"),
    (lambda k: k.__setitem__((2, 0), 1e-3), "pinhole"),
    (lambda k: k.__setitem__((0, 0), 0.0), "fx, fy > 0"),
    (lambda k: k.__setitem__((1, 1), -3.0), "fx, fy > 0"),
    (lambda k: k.__setitem__((0, 2), np.nan), "NaN or inf"),
])
def test_intrinsics_errors(edit, match):
    bad = K.copy()
    edit(bad)
    with pytest.raises(InputError, match=match) as e:
        check_intrinsics(bad, "intrinsics", 4, 6)
    assert str(e.value).startswith("intrinsics: ")
    per_view = np.stack([K, bad])
    with pytest.raises(InputError, match=r"^K\[1\]: "):
        check_intrinsics(per_view, "K", views=2)


def test_intrinsics_shape_and_type_errors():
    with pytest.raises(InputError, match="3x3 matrix of numbers"):
        check_intrinsics([["a"] * 3] * 3)
    with pytest.raises(InputError, match="3x3"):
        check_intrinsics(np.eye(4))
    with pytest.raises(InputError, match=r"K: expected shape \[3, 3\] or \[2, 3, 3\]"):
        check_intrinsics(np.stack([K] * 3), "K", views=2)


# -- images --------------------------------------------------------------------------------------

def test_images_pass_unchanged():
    for a in (np.zeros((4, 5, 3), np.uint8), np.zeros((4, 5), np.uint16),
              np.ones((4, 5, 4), np.float32), np.full((4, 5, 1), 1 + FLOAT_IMAGE_ATOL, np.float64)):
        assert check_images(a) is a
    batch = np.random.default_rng(0).random((2, 3, 4, 5)).astype(np.float32)
    assert check_images(batch, "reference_images", batch=True) is batch


@pytest.mark.parametrize("value, batch, match", [
    (np.zeros((4, 5, 2), np.uint8), False, "shape"),
    (np.zeros((0, 5, 3), np.uint8), False, "empty"),
    (np.zeros((4, 5, 3), np.int64), False, "dtype"),
    (np.zeros((4, 5, 3), bool), False, "dtype"),
    (np.full((4, 5, 3), np.inf, np.float32), False, "NaN or inf"),
    (np.full((4, 5, 3), 255.0, np.float32), False, "divide by 255"),
    ([[0, 1]], False, "numpy array"),
    (np.zeros((2, 4, 5, 3), np.float32), True, r"\[N, 3, H, W\]"),
    (np.zeros((0, 3, 4, 5), np.float32), True, r"\[N, 3, H, W\]"),
    (np.full((2, 3, 4, 5), 200.0, np.float32), True, "divide by 255"),
])
def test_image_errors_name_the_argument(value, batch, match):
    with pytest.raises(ImageError, match=match) as e:
        check_images(value, "images[1]", batch=batch)
    assert str(e.value).startswith("images[1]: ")
    assert isinstance(e.value, IrisError) and isinstance(e.value, ValueError)


def test_integer_check_names_the_argument_and_keeps_the_callers_error_type():
    assert check_integer(3, "samples") == 3 and type(check_integer(np.int64(3), "n")) is int
    assert check_integer(None, "top_k", allow_none=True) is None
    assert check_integer(0, "depth_window", minimum=0) == 0
    for bad, match in ((0, "positive integer, got 0"), (True, "True"), (2.0, "2.0"), ("3", "'3'"),
                       (None, "None"), (np.bool_(True), "True")):
        with pytest.raises(InputError, match=match) as e:
            check_integer(bad, "samples")
        assert str(e.value).startswith("samples: expected a positive integer, got")
    with pytest.raises(InputError, match="non-negative integer or None, got -1"):
        check_integer(-1, "depth_window", minimum=0, allow_none=True)
    with pytest.raises(InputError, match=r"an integer >= 4, got 3"):
        check_integer(3, "k", minimum=4)
    with pytest.raises(ImageError, match="height: expected a positive integer"):
        check_integer(-2, "height", error=ImageError)

"""iris_runtime.camera_io: transforms.json and COLMAP text, against a hand-computed camera."""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from iris_runtime.camera_io import (flip_opengl_opencv, quaternion_from_rotation,
                                    read_colmap_text, read_transforms_json,
                                    rotation_from_quaternion, write_colmap_text,
                                    write_transforms_json)
from iris_runtime.errors import InputError

# Hand-computed example. An OpenCV camera at c = (2, 0, 1) looking along world -x, with its x axis
# (right) along world +y and its y axis (down) along world -z:
#   world_from_cam = [x | y | z | c] = [(0,1,0) | (0,0,-1) | (-1,0,0) | (2,0,1)]
# OpenGL axes (y up, z backward) flip the y and z columns:
#   transform_matrix = [(0,1,0) | (0,0,1) | (1,0,0) | (2,0,1)]
# COLMAP stores world-to-camera: R_cam_from_world = R^T, t = -R^T c = (0, 1, 2), and
#   q(R_cam_from_world) = (w, x, y, z) = (0.5, 0.5, 0.5, -0.5)  [trace 0 -> w = 1/2; x = (R21-R12)/4w, ...]
WORLD_FROM_CAM = np.array([[0.0, 0.0, -1.0, 2.0],
                           [1.0, 0.0, 0.0, 0.0],
                           [0.0, -1.0, 0.0, 1.0],
                           [0.0, 0.0, 0.0, 1.0]])
TRANSFORM_MATRIX_GL = [[0.0, 0.0, 1.0, 2.0],
                       [1.0, 0.0, 0.0, 0.0],
                       [0.0, 1.0, 0.0, 1.0],
                       [0.0, 0.0, 0.0, 1.0]]
QVEC, TVEC = (0.5, 0.5, 0.5, -0.5), (0.0, 1.0, 2.0)
K_EX = np.array([[500.0, 0.0, 320.0], [0.0, 510.0, 240.0], [0.0, 0.0, 1.0]])


def _random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        q = rng.normal(size=4)
        T[i, :3, :3] = rotation_from_quaternion(q)
        T[i, :3, 3] = rng.normal(0, 3, 3)
    return T


def test_hand_example_is_consistent():
    R = WORLD_FROM_CAM[:3, :3]
    assert np.isclose(np.linalg.det(R), 1.0)
    np.testing.assert_array_equal(flip_opengl_opencv(WORLD_FROM_CAM), TRANSFORM_MATRIX_GL)
    np.testing.assert_allclose(quaternion_from_rotation(R.T), QVEC, atol=1e-15)
    np.testing.assert_allclose(-R.T @ WORLD_FROM_CAM[:3, 3], TVEC, atol=1e-15)
    # A point 1 unit in front of the camera is at c + z = (1, 0, 1).
    x_cam = np.linalg.inv(WORLD_FROM_CAM) @ [1.0, 0.0, 1.0, 1.0]
    np.testing.assert_allclose(x_cam, [0, 0, 1, 1], atol=1e-15)


def test_read_hand_written_transforms_json(tmp_path):
    doc = {"camera_model": "OPENCV", "fl_x": 500.0, "fl_y": 510.0, "cx": 320.0, "cy": 240.0,
           "w": 640, "h": 480,
           "frames": [{"file_path": "images/a.png", "transform_matrix": TRANSFORM_MATRIX_GL}]}
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    cams = read_transforms_json(tmp_path / "transforms.json")
    np.testing.assert_array_equal(cams.world_from_cam[0], WORLD_FROM_CAM)
    np.testing.assert_array_equal(cams.K[0], K_EX)
    assert cams.sizes.tolist() == [[480, 640]] and cams.names == ("images/a.png",)
    assert cams.index_of("a.png") == 0 and cams.index_of("./images/a.png") == 0
    assert cams.index_of("b.png") is None


def test_write_transforms_json_hand_example(tmp_path):
    p = write_transforms_json(tmp_path / "t.json", WORLD_FROM_CAM[None], K_EX, (480, 640), ["a.png"])
    doc = json.loads(p.read_text())
    assert doc["frames"][0]["transform_matrix"] == TRANSFORM_MATRIX_GL
    assert (doc["fl_x"], doc["fl_y"], doc["cx"], doc["cy"], doc["w"], doc["h"]) == \
        (500.0, 510.0, 320.0, 240.0, 640, 480)
    assert not [f for f in tmp_path.iterdir() if f.name.endswith(".tmp")]


def test_read_hand_written_colmap(tmp_path):
    (tmp_path / "cameras.txt").write_text(
        "# comment\n1 PINHOLE 640 480 500 510 320 240\n2 SIMPLE_PINHOLE 640 480 500 320 240\n")
    (tmp_path / "images.txt").write_text(
        "# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        f"7 {' '.join(map(str, QVEC))} {' '.join(map(str, TVEC))} 1 a.png\n"
        "10.5 20.5 -1 11.0 12.0 3\n"                      # POINTS2D line
        f"3 1 0 0 0 0 0 0 2 b.png\n"                       # identity, no POINTS2D line at all
        "\n")
    cams = read_colmap_text(tmp_path)
    assert cams.names == ("a.png", "b.png")
    np.testing.assert_allclose(cams.world_from_cam[0], WORLD_FROM_CAM, atol=1e-15)
    np.testing.assert_array_equal(cams.world_from_cam[1], np.eye(4))
    np.testing.assert_array_equal(cams.K[0], K_EX)
    np.testing.assert_array_equal(cams.K[1], [[500, 0, 320], [0, 500, 240], [0, 0, 1]])


def test_write_colmap_hand_example(tmp_path):
    write_colmap_text(tmp_path, WORLD_FROM_CAM[None], K_EX, (480, 640), ["a.png"])
    cams = (tmp_path / "cameras.txt").read_text().splitlines()
    assert "1 PINHOLE 640 480 500.0 510.0 320.0 240.0" in cams
    imgs = (tmp_path / "images.txt").read_text().splitlines()
    assert "1 0.5 0.5 0.5 -0.5 0.0 1.0 2.0 1 a.png" in imgs
    assert (tmp_path / "points3D.txt").exists()


@pytest.mark.parametrize("shared", [True, False])
def test_round_trips(tmp_path, shared):
    V = 7
    T = _random_poses(V)
    rng = np.random.default_rng(1)
    if shared:
        K = K_EX
    else:
        K = np.stack([np.array([[rng.uniform(50, 900), 0, rng.uniform(0, 640)],
                                [0, rng.uniform(50, 900), rng.uniform(0, 480)], [0, 0, 1]])
                      for _ in range(V)])
    names = [f"frame_{i:03d}.png" for i in range(V)]
    Kv = np.broadcast_to(K, (V, 3, 3))
    write_transforms_json(tmp_path / "transforms.json", T, K, (480, 640), names)
    a = read_transforms_json(tmp_path / "transforms.json")
    write_colmap_text(tmp_path / "sparse", T, K, (480, 640), names)
    b = read_colmap_text(tmp_path / "sparse")
    for cams in (a, b):
        assert cams.names == tuple(names)
        np.testing.assert_allclose(cams.world_from_cam, T, atol=1e-9, rtol=0)
        np.testing.assert_allclose(cams.K, Kv, atol=1e-9, rtol=0)
        assert (cams.sizes == [480, 640]).all()
    np.testing.assert_array_equal(a.world_from_cam, T)          # JSON floats are exact


def test_quaternion_round_trip_near_180_degrees():
    for axis in np.eye(3):
        for ang in (np.pi, np.pi - 1e-9, 1e-12, 0.0):
            w, xyz = np.cos(ang / 2), np.sin(ang / 2) * axis
            R = rotation_from_quaternion([w, *xyz])
            q = quaternion_from_rotation(R)
            np.testing.assert_allclose(rotation_from_quaternion(q), R, atol=1e-12)
            assert q[0] >= 0


def test_transforms_json_variants(tmp_path):
    M = TRANSFORM_MATRIX_GL
    doc = {"camera_angle_x": 2 * np.arctan(320 / 500.0),
           "frames": [{"file_path": "./train/r_0", "transform_matrix": M},
                      {"file_path": "./train/r_1", "transform_matrix": M[:3], "fl_x": 300.0,
                       "w": 100, "h": 50, "k1": 0.1}]}
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="image size"):
        read_transforms_json(tmp_path / "transforms.json")
    with pytest.warns(UserWarning, match="distortion"):
        cams = read_transforms_json(tmp_path / "transforms.json", image_size=lambda name: (480, 640))
    np.testing.assert_allclose(cams.K[0], [[500, 0, 320], [0, 500, 240], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(cams.K[1], [[300, 0, 50], [0, 300, 25], [0, 0, 1]])
    np.testing.assert_array_equal(cams.world_from_cam[1], WORLD_FROM_CAM)
    assert cams.index_of("train/r_1.png") == 1


@pytest.mark.parametrize("content,match", [
    ("{not json", "not valid JSON"),
    ('{"frames": []}', "non-empty 'frames'"),
    ('{"w": 4, "h": 4, "fl_x": 2, "frames": [{"file_path": "a.png", "transform_matrix": [[1, 0], [0, 1]]}]}',
     "4x4"),
    ('{"w": 4, "h": 4, "fl_x": 2, "frames": [{"file_path": "a.png", "transform_matrix": '
     '[[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]]}]}', "rigid"),
    ('{"w": 4, "h": 4, "frames": [{"file_path": "a.png", "transform_matrix": '
     '[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}', "focal"),
])
def test_bad_transforms_json(tmp_path, content, match):
    p = tmp_path / "transforms.json"
    p.write_text(content)
    with pytest.raises(InputError, match=match) as e:
        read_transforms_json(p)
    assert str(p) in str(e.value)


def test_bad_colmap(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_colmap_text(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 WEIRD 640 480 1 2 3\n")
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")
    with pytest.raises(InputError, match="unknown camera model") as e:
        read_colmap_text(tmp_path)
    assert "cameras.txt:1" in str(e.value)
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 640 480 1 2 3\n")
    with pytest.raises(InputError, match="needs 4 parameters"):
        read_colmap_text(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 OPENCV 640 480 500 500 320 240 0.1 0 0 0\n")
    with pytest.warns(UserWarning, match="distortion"):
        cams = read_colmap_text(tmp_path)
    np.testing.assert_array_equal(cams.K[0], [[500, 0, 320], [0, 500, 240], [0, 0, 1]])
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 2 a.png\n\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(InputError, match="CAMERA_ID 2"):
            read_colmap_text(tmp_path)


def test_writers_validate(tmp_path):
    T = _random_poses(2)
    names = ["a.png", "b.png"]
    bad = T.copy()
    bad[0, :3, :3] *= 2
    with pytest.raises(InputError, match=r"world_from_cam\[0\]: expected a rigid"):
        write_transforms_json(tmp_path / "t.json", bad, K_EX, (480, 640), names)
    with pytest.raises(InputError, match="world_from_cam: expected an array of shape"):
        write_colmap_text(tmp_path, T[0], K_EX, (480, 640), names)
    with pytest.raises(InputError, match="image_names"):
        write_colmap_text(tmp_path, T, K_EX, (480, 640), ["a.png"])
    with pytest.raises(InputError, match="K: expected shape"):
        write_colmap_text(tmp_path, T, np.eye(4), (480, 640), names)
    with pytest.raises(InputError, match="white space"):
        write_colmap_text(tmp_path, T, K_EX, (480, 640), ["a b.png", "c.png"])
    nan = T.copy()
    nan[1, 0, 3] = np.nan
    with pytest.raises(InputError, match="NaN"):
        write_transforms_json(tmp_path / "t.json", nan, K_EX, (480, 640), names)
    assert not list(tmp_path.iterdir())                      # nothing half-written


def test_writers_refuse_skew_and_non_pinhole_k(tmp_path):
    T = _random_poses(2)
    names = ["a.png", "b.png"]
    for K in ([[500, 1, 320], [0, 500, 240], [0, 0, 1]], [[500, 0, 320], [0, 500, 240], [0, 0, 2]],
              [[500, 0, 320], [0, -5, 240], [0, 0, 1]]):
        for write in (lambda: write_transforms_json(tmp_path / "t.json", T, K, (480, 640), names),
                      lambda: write_colmap_text(tmp_path / "c", T, K, (480, 640), names)):
            with pytest.raises(InputError, match="K: expected pinhole"):
                write()
    assert not list(tmp_path.iterdir())


def test_writers_take_what_the_one_rigidity_check_takes_and_write_it_unchanged(tmp_path):
    """float32 poses (the encoder's, rigid to ~1e-7) and poses off by 5e-5 < RIGID_ATOL are
    written as given (iris-render no longer snaps them first) and read back bit for bit."""
    T = _random_poses(3, seed=4)
    T32 = T.astype(np.float32).astype(np.float64)
    near = T.copy()
    near[1, :3, :3] *= 1 + 2.5e-5                       # |R^T R - I| = 5e-5
    for poses in (T32, near):
        write_transforms_json(tmp_path / "t.json", poses, K_EX, (480, 640), ["a", "b", "c"])
        np.testing.assert_array_equal(read_transforms_json(tmp_path / "t.json").world_from_cam,
                                      poses)
    far = T.copy()
    far[1, :3, :3] *= 1 + 1e-4                          # 2e-4 > RIGID_ATOL
    with pytest.raises(InputError, match=r"world_from_cam\[1\]: .*not orthonormal"):
        write_colmap_text(tmp_path / "c", far, K_EX, (480, 640), ["a", "b", "c"])


def test_transforms_json_with_few_decimals_is_snapped_to_rigid(tmp_path):
    """The one reader-side relaxation (validation.snap_world_from_cam): a rotation printed with 3
    decimals (rigid to ~1e-3) becomes the nearest rigid transform; further off is refused."""
    from iris_runtime.validation import RIGID_ATOL, SNAP_ATOL, check_world_from_cam, rigidity_error
    c, s = np.cos(0.5), np.sin(0.5)
    M = np.array([[c, 0, s, 1.0], [0, 1, 0, 2.0], [-s, 0, c, 3.0], [0, 0, 0, 1]])
    M3 = np.round(M, 3)
    assert RIGID_ATOL < rigidity_error(M3) <= SNAP_ATOL
    doc = {"fl_x": 500.0, "w": 640, "h": 480,
           "frames": [{"file_path": "a.png", "transform_matrix": M3.tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    got = read_transforms_json(tmp_path / "transforms.json").world_from_cam[0]
    assert rigidity_error(got) < 1e-12
    check_world_from_cam(got)                                    # passes the strict check
    np.testing.assert_allclose(got, M3 @ np.diag([1.0, -1, -1, 1]), atol=1e-3)
    np.testing.assert_array_equal(got[:3, 3], M3[:3, 3])        # translation kept
    bad = M.copy()
    bad[:3, :3] *= 1.002                                         # a scale, not rounding
    doc["frames"][0]["transform_matrix"] = bad.tolist()
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"frames\[0\]\.transform_matrix: expected a rigid"):
        read_transforms_json(tmp_path / "transforms.json")

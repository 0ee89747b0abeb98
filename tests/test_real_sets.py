"""scripts/real_sets.py: the real evaluation sets built from a fake ViSP tree (frame lists, RGB,
cameras and their convention, atomic output, typed errors), the motion check on made-up
sequences, and the real Debian package when it is installed."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from iris_runtime.camera_io import read_transforms_json
from iris_runtime.errors import InputError

from . import conftest

REPO = Path(__file__).resolve().parents[1]
real_sets = conftest.load_script("real_sets")


def look_at(centre, target=(0.0, 0.0, 0.0)):
    """OpenCV world_from_cam at ``centre`` looking at ``target`` (world z up)."""
    c = np.asarray(centre, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = c
    return T


def fake_castle_pose(frame):
    a = 0.05 * frame
    return look_at((0.6 * np.cos(a), 0.6 * np.sin(a), 0.3 + 0.01 * frame))


@pytest.fixture(scope="module")
def fake_visp(tmp_path_factory):
    """A ViSP-images tree with the files the sets read: grey frames whose value encodes the
    frame number, Castle-simu poses written as cMo, and its config."""
    root = tmp_path_factory.mktemp("ViSP-images")
    rng = np.random.default_rng(0)

    def frame(h, w, k):
        im = rng.integers(0, 200, (h, w), dtype=np.uint8)
        im[0, 0] = k                        # the frame number, to check which file went where
        return im

    (root / "cube").mkdir()
    for k in range(80):
        cv2.imwrite(str(root / "cube" / f"image.{k:04d}.pgm"), frame(288, 384, k))
    castle = root / "mbt-depth" / "Castle-simu"
    for sub in ("Images", "CameraPose", "Config"):
        (castle / sub).mkdir(parents=True)
    for k in range(1, 41):
        cv2.imwrite(str(castle / "Images" / f"Image_{k:04d}.pgm"), frame(480, 640, k))
        np.savetxt(castle / "CameraPose" / f"Camera_{k:03d}.txt", np.linalg.inv(fake_castle_pose(k)))
    (castle / "Config" / "chateau.xml").write_text(
        "<?xml version='1.0'?><conf><camera><px>700</px><py>700</py><u0>321</u0><v0>239</v0>"
        "</camera></conf>")
    (root / "mbt-depth" / "castel" / "castel").mkdir(parents=True)
    for k in range(30):
        cv2.imwrite(str(root / "mbt-depth" / "castel" / "castel" / f"image_{k:04d}.pgm"),
                    frame(480, 640, k))
    return root


@pytest.fixture(scope="module")
def built(fake_visp, tmp_path_factory):
    out = tmp_path_factory.mktemp("sets") / "real"
    doc = real_sets.build(out, fake_visp)
    return out, doc


def test_scene_folders_and_frame_lists(built):
    out, doc = built
    expected = {
        "cube": {"0_start18_step2": range(18, 33, 2), "1_start33_step2": range(33, 48, 2),
                 "2_start48_step3": range(48, 70, 3), "3_start20_step4": range(20, 49, 4)},
        "castle": {"0_frames01-36_step5": range(1, 37, 5), "1_frames21-39_step2": range(21, 40, 2)},
        "castel": {"0_frames02-29": (2, 6, 10, 14, 17, 21, 25, 29)},
    }
    assert json.loads((out / "sets.json").read_text()) == doc
    assert sorted(p.name for p in out.iterdir()) == ["castel", "castle", "cube", "sets.json"]
    for name, scenes in expected.items():
        assert sorted(p.name for p in (out / name).iterdir()) == list(scenes)   # listed order
        for scene, frames in scenes.items():
            frames = list(frames)
            assert len(frames) in (8, 10) and doc["sets"][name]["scenes"][scene]["frames"] == frames
            pngs = sorted(p.name for p in (out / name / scene).glob("*.png"))
            assert pngs == [f"{f:04d}.png" for f in frames]          # zero-padded: sorted = Seq
            for f in (frames[0], frames[-1]):
                rgb = cv2.imread(str(out / name / scene / f"{f:04d}.png"), cv2.IMREAD_UNCHANGED)
                assert rgb.ndim == 3 and rgb.shape[2] == 3          # grey became RGB
                assert (rgb[..., 0] == rgb[..., 1]).all() and (rgb[..., 1] == rgb[..., 2]).all()
                assert rgb[0, 0, 0] == f                            # the right source frame
            has_cameras = (out / name / scene / "transforms.json").is_file()
            assert has_cameras == (name == "castle")
    assert doc["sets"]["cube"]["scenes"]["0_start18_step2"]["files"][0] == "cube/image.0018.pgm"


def test_castle_cameras_are_the_inverse_of_the_files_cMo(built):
    out, _ = built
    for scene, frames in (("0_frames01-36_step5", range(1, 37, 5)), ("1_frames21-39_step2", range(21, 40, 2))):
        cams = read_transforms_json(out / "castle" / scene / "transforms.json")
        truth = np.stack([fake_castle_pose(f) for f in frames])
        np.testing.assert_allclose(cams.world_from_cam, truth, atol=1e-12)
        # The pixel convention: ViSP counts pixel centres from 0, IRIS from 0.5.
        np.testing.assert_allclose(cams.K[0], [[700, 0, 321.5], [0, 700, 239.5], [0, 0, 1]])
        assert cams.sizes.tolist() == [[480, 640]] * len(truth)
        assert cams.names == tuple(f"{f:04d}.png" for f in frames)


def test_loaded_castle_scene_has_the_true_focal_at_model_resolution(built):
    from iris_train.data import load_dataset_folder
    scenes = load_dataset_folder(built[0] / "castle", size=(64, 64))
    for s in scenes:
        # 640x480 -> centre crop 480x480 -> 64x64: fx = 700 * 64 / 480.
        np.testing.assert_allclose(s.K[:, 0, 0], 700 * 64 / 480)
        np.testing.assert_allclose(s.K[:, 0, 2], (321.5 - 80) * 64 / 480)


def test_output_is_replaced_only_with_force_and_atomically(fake_visp, tmp_path):
    out = tmp_path / "real"
    real_sets.build(out, fake_visp, sets=("castle",))
    with pytest.raises(InputError, match="--force"):
        real_sets.build(out, fake_visp, sets=("cube",))
    assert sorted(p.name for p in out.iterdir()) == ["castle", "sets.json"]
    real_sets.build(out, fake_visp, sets=("cube",), force=True)
    assert sorted(p.name for p in out.iterdir()) == ["cube", "sets.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["real"]     # no temporary left


def test_bad_arguments_raise_typed_errors(fake_visp, tmp_path):
    with pytest.raises(InputError, match="visp-images-data"):
        real_sets.build(tmp_path / "a", tmp_path)                     # not a ViSP tree
    with pytest.raises(InputError, match="--sets"):
        real_sets.build(tmp_path / "b", fake_visp, sets=("cube", "moon"))
    with pytest.raises(InputError, match="--sets"):
        real_sets.build(tmp_path / "c", fake_visp, sets=())
    broken = tmp_path / "broken"
    (broken / "cube").mkdir(parents=True)
    with pytest.raises(InputError, match="missing source frames"):
        real_sets.build(tmp_path / "d", broken, sets=("cube",))
    assert not (tmp_path / "d").exists() and not list(tmp_path.glob(".d.*"))
    bad_xml = tmp_path / "chateau.xml"
    bad_xml.write_text("<conf><camera><px>700</px></camera></conf>")
    with pytest.raises(InputError, match="px, py, u0, v0"):
        real_sets.read_visp_intrinsics(bad_xml)
    bad_pose = tmp_path / "Camera_001.txt"
    bad_pose.write_text("1 0 0\n0 1 0\n")
    with pytest.raises(InputError, match="4x4"):
        real_sets.read_castle_pose(bad_pose)
    assert real_sets.main(["--out", str(tmp_path / "e"), "--visp", str(tmp_path)]) == 2


def test_motion_check_tells_a_moving_camera_from_a_moving_object():
    """A camera panning over a still texture moves the border and one rigid motion explains the
    flow; a still camera watching a patch move leaves the border still and every pair still;
    a repeated frame is a still pair."""
    rng = np.random.default_rng(1)
    world = cv2.GaussianBlur(rng.integers(0, 256, (300, 700), dtype=np.uint8), (5, 5), 1.5)
    pan = [world[20:260, 5 * k:5 * k + 320].copy() for k in range(16)]      # 5 px a frame
    pan = pan[:2] + [pan[1]] + pan[2:]                                # one repeated frame
    object_moves = []
    for k in range(16):
        frame = world[20:260, 100:420].copy()
        frame[80:160, 60 + 8 * k:140 + 8 * k] = world[0:80, 600:680]
        object_moves.append(frame)
    moving = real_sets.motion_check(pan, gap=4)
    still = real_sets.motion_check(object_moves, gap=4)
    assert moving["still"] == [1]
    # 4 frames of 5 px on a 320-px frame: 6.25 % of the width (a few pairs span the repeat)
    assert moving["border_flow"] == pytest.approx(6.25, abs=0.7) and moving["rigid"] > 0.95
    # The object covers a fifth of the frame: by the median flow no pair moves.
    assert still["border_flow"] < 0.05 and still["still"] == list(range(15))
    with pytest.raises(InputError, match="at least 2"):
        real_sets.motion_check(pan[:1])


needs_visp = pytest.mark.skipif(not (real_sets.VISP_ROOT / "mbt-depth" / "Castle-simu").is_dir(),
                                reason="visp-images-data is not installed (apt-get install -y "
                                       "visp-images-data)")


@needs_visp
def test_real_castle_poses_are_cMo_by_epipolar_geometry():
    """SIFT matches between Castle-simu frames lie on the epipolar lines of the poses read as
    cMo (under a pixel), not as oMc."""
    result = real_sets.castle_pose_check(real_sets.VISP_ROOT, pairs=((1, 6), (21, 31)))
    for r in result.values():
        assert r["matches"] >= 20 and r["cMo"] < 1.0 and r["oMc"] > 10.0


@needs_visp
def test_real_package_builds_and_its_cameras_explain_the_images(tmp_path):
    out = tmp_path / "real"
    doc = real_sets.build(out, sets=("castle", "cube"))
    assert doc["version"] and set(doc["sets"]) == {"castle", "cube"}
    # The written cameras (not only the source files) satisfy the epipolar constraint.
    folder = out / "castle" / "0_frames01-36_step5"
    cams = read_transforms_json(folder / "transforms.json")
    sift = cv2.SIFT_create()
    feats = [sift.detectAndCompute(cv2.imread(str(folder / n), cv2.IMREAD_GRAYSCALE), None)
             for n in ("0001.png", "0006.png")]
    good = [m for m, n in cv2.BFMatcher().knnMatch(feats[0][1], feats[1][1], k=2)
            if m.distance < 0.7 * n.distance]
    p = np.float64([feats[0][0][m.queryIdx].pt for m in good]) + 0.5
    q = np.float64([feats[1][0][m.trainIdx].pt for m in good]) + 0.5
    T = np.linalg.inv(cams.world_from_cam[1]) @ cams.world_from_cam[0]       # camera 0 -> 1
    t = T[:3, 3]
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ T[:3, :3]
    Ki = np.linalg.inv(cams.K[0])
    lines = np.c_[p, np.ones(len(p))] @ (Ki.T @ E @ Ki).T
    d = np.abs((np.c_[q, np.ones(len(q))] * lines).sum(1)) / np.hypot(lines[:, 0], lines[:, 1])
    assert len(d) >= 20 and np.median(d) < 1.0
    # The cube's still stretches are where the issue says they are, and the set's frames move.
    root = real_sets.VISP_ROOT / "cube"
    frames = [cv2.imread(str(root / f"image.{k:04d}.pgm"), cv2.IMREAD_GRAYSCALE) for k in range(80)]
    check = real_sets.motion_check(frames)
    assert set(range(0, 16)) <= set(check["still"]) and set(range(71, 79)) <= set(check["still"])
    assert not set(check["still"]) & set(range(17, 70))

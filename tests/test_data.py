"""iris_train.data: the synthetic scene cache, the seed splits, and loading folders of photos."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("pyrender")

import cv2  # noqa: E402

from iris_runtime.camera_io import write_colmap_text, write_transforms_json  # noqa: E402
from iris_runtime.errors import ImageError, InputError  # noqa: E402
from iris_runtime.images import plan_crop_resize  # noqa: E402
from iris_train.data import (HELDOUT_SEEDS, TRAIN_SEEDS, SyntheticScenes,  # noqa: E402
                             default_cache_dir, load_dataset_folder, load_scene,
                             load_scene_folder, pregenerate, relative_to_first, save_scene)
from iris_train.synthetic import render_scene  # noqa: E402


def _same(a, b):
    for f in ("images", "world_from_cam", "K", "depth"):
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), f


def test_seed_splits_are_disjoint():
    assert len(HELDOUT_SEEDS) == 16 and len(TRAIN_SEEDS) == 100_000
    assert not set(HELDOUT_SEEDS) & set(TRAIN_SEEDS)


def test_default_cache_dir(monkeypatch, tmp_path):
    monkeypatch.setenv("IRIS_CACHE_DIR", str(tmp_path))
    assert default_cache_dir((64, 48)) == tmp_path / "synthetic" / "64x48"
    monkeypatch.delenv("IRIS_CACHE_DIR")
    assert str(default_cache_dir()).endswith(".cache/iris/synthetic/64x64")


def test_cache_writes_once_and_reads_back(tmp_path):
    ds = SyntheticScenes([3, 4], n_views=3, size=(32, 32), cache_dir=tmp_path)
    assert len(ds) == 2 and not ds.is_cached(3)
    a = ds[0]
    assert ds.is_cached(3) and not ds.is_cached(4)
    assert a.images.shape == (3, 32, 32, 3)
    mtime = ds.path(3).stat().st_mtime_ns
    b = ds[0]
    assert ds.path(3).stat().st_mtime_ns == mtime            # read, not rewritten
    _same(a, b)
    assert b.meta["seed"] == 3 and b.meta["kind"] in ("turntable", "room")
    assert [p.name for p in tmp_path.iterdir()] == [ds.path(3).name]     # no temp files left
    with pytest.raises(IndexError):
        ds[2]


def test_corrupt_cache_file_is_regenerated(tmp_path):
    ds = SyntheticScenes([5], n_views=2, size=(32, 32), cache_dir=tmp_path)
    good = ds[0]
    ds.path(5).write_bytes(b"PK\x03\x04 broken")
    with pytest.raises(InputError, match="not a readable cached scene"):
        load_scene(ds.path(5))
    with pytest.warns(UserWarning, match="regenerating"):
        again = ds[0]
    _same(good, again)
    load_scene(ds.path(5))                                   # repaired on disk


def test_pregenerate_with_two_processes_matches_direct_render(tmp_path):
    stats = pregenerate([21, 22, 23], n_views=2, size=(32, 32), cache_dir=tmp_path, workers=2,
                        progress=False)
    assert stats["generated"] == 3
    ds = SyntheticScenes([21, 22, 23], n_views=2, size=(32, 32), cache_dir=tmp_path)
    assert all(ds.is_cached(s) for s in (21, 22, 23))
    # Bitwise the same scene whichever process rendered it.
    _same(load_scene(ds.path(22)), render_scene(22, n_views=2, size=(32, 32)))
    again = pregenerate([21, 22, 23], n_views=2, size=(32, 32), cache_dir=tmp_path, workers=2,
                        progress=False)
    assert again["generated"] == 0 and again["cached"] == 3


def test_pregenerate_verify_replaces_stale_files(tmp_path):
    """A cached file that no longer matches the generator (e.g. written by older code) is replaced."""
    ds = SyntheticScenes([41, 42], n_views=2, size=(16, 16), cache_dir=tmp_path)
    ds[0], ds[1]
    save_scene(ds.path(41), ds[1])                            # seed 41's file now holds seed 42
    r = pregenerate([41, 42], n_views=2, size=(16, 16), cache_dir=tmp_path, workers=1,
                    progress=False, verify=True)
    assert r["replaced"] == 1 and r["generated"] == 0
    _same(load_scene(ds.path(41)), render_scene(41, n_views=2, size=(16, 16)))


def test_relative_to_first():
    s = render_scene(8, n_views=3, size=(16, 16))
    T = relative_to_first(s.world_from_cam)
    np.testing.assert_array_equal(T[0], np.eye(4))
    # relative poses between any two views are unchanged
    rel = np.linalg.inv(s.world_from_cam[1]) @ s.world_from_cam[2]
    np.testing.assert_allclose(np.linalg.inv(T[1]) @ T[2], rel, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# folders of photos
# ---------------------------------------------------------------------------------------------

def test_folder_of_mixed_images(tmp_path):
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 256, (80, 120, 3), dtype=np.uint8)).save(tmp_path / "b.png")
    Image.fromarray(rng.integers(0, 256, (100, 100), dtype=np.uint8)).save(tmp_path / "a.jpg")
    Image.fromarray(rng.integers(0, 256, (40, 30, 4), dtype=np.uint8)).save(tmp_path / "c.png")
    g16 = rng.integers(0, 65536, (70, 50), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "d.png"), g16)
    (tmp_path / "notes.txt").write_text("ignored")
    scene = load_scene_folder(tmp_path, size=(64, 64))
    assert scene.names == ("a.jpg", "b.png", "c.png", "d.png")            # file-name order
    assert scene.images.shape == (4, 64, 64, 3) and scene.images.dtype == np.uint8
    assert scene.world_from_cam is None and scene.K is None and scene.depth is None
    assert [(c.src_h, c.src_w) for c in scene.crops] == [(100, 100), (80, 120), (40, 30), (70, 50)]
    assert scene.crops[1] == plan_crop_resize(80, 120, 64, 64)
    # grayscale and 16-bit inputs become three equal channels
    assert (scene.images[3][..., 0] == scene.images[3][..., 2]).all()


def test_corrupt_image_in_folder_names_the_file(tmp_path):
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(tmp_path / "a.png")
    (tmp_path / "b.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    with pytest.raises(ImageError, match="b.jpg"):
        load_scene_folder(tmp_path)


def test_folder_errors(tmp_path):
    with pytest.raises(InputError, match="not a folder"):
        load_scene_folder(tmp_path / "nope")
    with pytest.raises(InputError, match="no images"):
        load_scene_folder(tmp_path)
    with pytest.raises(InputError, match="no scene folders"):
        load_dataset_folder(tmp_path)


@pytest.fixture(scope="module")
def wide_scene():
    """A rendered 48x80 scene with known cameras, to be saved as a user's folder."""
    return render_scene(31, n_views=3, size=(48, 80), markers=True)


def _save_images(folder, scene, sub="images"):
    (folder / sub).mkdir(parents=True, exist_ok=True)
    names = []
    for v, img in enumerate(scene.images):
        name = f"{sub}/frame_{v:02d}.png"
        Image.fromarray(img).save(folder / name)
        names.append(name)
    return names


@pytest.mark.parametrize("fmt", ["transforms", "colmap"])
def test_folder_with_cameras(tmp_path, wide_scene, fmt):
    s = wide_scene
    names = _save_images(tmp_path, s)
    if fmt == "transforms":
        write_transforms_json(tmp_path / "transforms.json", s.world_from_cam, s.K, (48, 80), names)
    else:   # COLMAP usually names images relative to the images folder
        write_colmap_text(tmp_path / "sparse" / "0", s.world_from_cam, s.K, (48, 80),
                          [n.split("/")[-1] for n in names])
    scene = load_scene_folder(tmp_path, size=(32, 32))
    assert scene.images.shape == (3, 32, 32, 3)
    np.testing.assert_allclose(scene.world_from_cam, s.world_from_cam, atol=1e-9, rtol=0)
    # 48x80 -> centre crop 48x48 at x0 = 16 -> scale 32/48
    Kexp = np.diag([32 / 48, 32 / 48, 1.0]) @ np.array([[1, 0, -16], [0, 1, 0], [0, 0, 1.0]]) @ s.K
    np.testing.assert_allclose(scene.K, np.broadcast_to(Kexp, (3, 3, 3)), atol=1e-9)
    # The adjusted K still projects the known markers onto the markers in the loaded images.
    X = np.asarray(s.meta["markers"]["centers_world"])
    for v in range(3):
        Xc = (np.linalg.inv(scene.world_from_cam[v]) @ np.c_[X, np.ones(len(X))].T)[:3].T
        p = (scene.K[v] @ Xc.T).T
        uv = p[:, :2] / p[:, 2:]
        cov = s.meta["marker_coverage"][v]                   # [M, 48, 80] in the original image
        for m in range(len(X)):
            if cov[m].sum() < 2 or not (4 < uv[m, 0] < 28 and 4 < uv[m, 1] < 28):
                continue
            j, i = np.meshgrid(np.arange(80) + 0.5, np.arange(48) + 0.5)
            c = np.array([(cov[m] * j).sum(), (cov[m] * i).sum()]) / cov[m].sum()
            np.testing.assert_allclose(scene.crops[v].to_output(c), uv[m], atol=0.5)


def test_camera_missing_for_an_image(tmp_path, wide_scene):
    names = _save_images(tmp_path, wide_scene)
    write_transforms_json(tmp_path / "transforms.json", wide_scene.world_from_cam[:2], wide_scene.K,
                          (48, 80), names[:2])
    with pytest.raises(InputError, match="frame_02.png: no camera"):
        load_scene_folder(tmp_path)


def test_cameras_for_resized_photos_are_rescaled(tmp_path, wide_scene):
    """Cameras computed for 48x80 photos, photos stored at 96x160: K scales by 2 first."""
    s = wide_scene
    (tmp_path / "images").mkdir()
    names = []
    for v, img in enumerate(s.images):
        names.append(f"images/{v}.png")
        Image.fromarray(cv2.resize(img, (160, 96), interpolation=cv2.INTER_LINEAR)).save(tmp_path / names[-1])
    write_transforms_json(tmp_path / "transforms.json", s.world_from_cam, s.K, (48, 80), names)
    big = load_scene_folder(tmp_path, size=(32, 32))
    shutil_dir = tmp_path / "orig"
    shutil_dir.mkdir()
    onames = _save_images(shutil_dir, s)
    write_transforms_json(shutil_dir / "transforms.json", s.world_from_cam, s.K, (48, 80), onames)
    small = load_scene_folder(shutil_dir, size=(32, 32))
    np.testing.assert_allclose(big.K, small.K, atol=1e-9)


def test_load_dataset_folder(tmp_path):
    for name in ("scene_b", "scene_a"):
        d = tmp_path / name
        d.mkdir()
        for k in range(2):
            Image.fromarray(np.full((20, 30, 3), 40 * k, np.uint8)).save(d / f"{k}.png")
    (tmp_path / "empty").mkdir()
    scenes = load_dataset_folder(tmp_path, size=(16, 16))
    assert [s.meta["path"].rsplit("/", 1)[-1] for s in scenes] == ["scene_a", "scene_b"]
    assert all(s.images.shape == (2, 16, 16, 3) for s in scenes)


# ---------------------------------------------------------------------------------------------
# capture kinds: splits, mixes, the render cache at a larger size, the CLI
# ---------------------------------------------------------------------------------------------

def test_capture_splits_are_disjoint_from_training_and_each_other():
    from iris_train.data import CAPTURE_HELDOUT_SEEDS, CAPTURE_VALIDATION_SEEDS, VALIDATION_SEEDS
    assert len(CAPTURE_HELDOUT_SEEDS) == 16 and not set(CAPTURE_HELDOUT_SEEDS) & set(TRAIN_SEEDS)
    assert not set(CAPTURE_VALIDATION_SEEDS) & (set(VALIDATION_SEEDS) | set(CAPTURE_HELDOUT_SEEDS))
    # Training runs use seeds below min(VALIDATION_SEEDS) (iris_train.train refuses more).
    assert min(CAPTURE_VALIDATION_SEEDS) > min(VALIDATION_SEEDS)
    from iris_train.synthetic import capture_kind
    kinds = [capture_kind(s) for s in CAPTURE_HELDOUT_SEEDS]
    assert {k: kinds.count(k) for k in set(kinds)} == {"walk": 4, "orbit": 4, "handheld": 4, "indoor": 4}


def test_mix_parsing_and_per_seed_kinds():
    from iris_train.data import kind_of_seed, parse_mix
    mix = parse_mix("walk=3, orbit=1,handheld")
    assert mix == {"walk": 3.0, "orbit": 1.0, "handheld": 1.0}
    kinds = [kind_of_seed(s, mix) for s in range(2000)]
    assert abs(kinds.count("walk") / 2000 - 0.6) < 0.05 and set(kinds) == set(mix)
    assert kinds == [kind_of_seed(s, mix) for s in range(2000)]
    for bad in ("forest=1", "walk=0", "walk=x", "capture=1", "walk=nan"):
        with pytest.raises(InputError, match="mix"):
            parse_mix(bad)
    with pytest.raises(InputError, match="kind"):
        SyntheticScenes([0], kind="forest")


def test_render_cache_serves_smaller_sizes(tmp_path):
    """A 64 render cache (clean, float16 depth) gives 32 and 16 scenes by area downsampling with
    photometric effects; ``clean=True`` gives the plain downsample; poses and K as a direct render."""
    from iris_train.synthetic import downsample_scene
    ds = SyntheticScenes([8, 9], n_views=2, size=(16, 16), cache_dir=tmp_path, kind="capture",
                         render_size=(64, 64))
    s = ds[0]
    assert s.images.shape == (2, 16, 16, 3) and s.meta["photometric"] and s.depth.dtype == np.float32
    assert ds.path(8).name == "scene_0000008_v2_g3.npz"
    cached = load_scene(ds.path(8))
    assert cached.images.shape == (2, 64, 64, 3)
    direct = render_scene(8, n_views=2, size=(16, 16), kind="capture")
    np.testing.assert_allclose(s.K, direct.K, rtol=1e-14)
    np.testing.assert_array_equal(s.world_from_cam, direct.world_from_cam)
    clean = SyntheticScenes([8], n_views=2, size=(32, 32), cache_dir=tmp_path, kind="capture",
                            render_size=(64, 64), clean=True)[0]
    np.testing.assert_array_equal(clean.images, downsample_scene(cached, 2).images)
    assert not np.array_equal(SyntheticScenes([8], 2, (32, 32), tmp_path, "capture", (64, 64))[0].images,
                              clean.images)
    kept = SyntheticScenes([8, 9], 2, (16, 16), tmp_path, "capture", (64, 64), memory=1)
    first = kept[0]
    assert kept[0] is first and kept[1] is not first and kept[0] is not first   # LRU of one
    _same(first, s)
    with pytest.raises(InputError, match="render_size"):
        SyntheticScenes([8], size=(16, 16), render_size=(40, 40), kind="capture")


def test_classic_scenes_from_a_larger_render_are_downsampled_clean(tmp_path):
    """The classic kinds at ``render_size`` twice ``size``: the area downsample of the cached
    render, no photometric effects, poses and K as a direct render at ``size``."""
    from iris_train.synthetic import downsample_scene
    ds = SyntheticScenes([5], n_views=2, size=(16, 16), cache_dir=tmp_path, render_size=(32, 32))
    s = ds[0]
    cached = load_scene(ds.path(5))
    assert cached.images.shape == (2, 32, 32, 3) and s.images.shape == (2, 16, 16, 3)
    assert "photometric" not in s.meta
    np.testing.assert_array_equal(s.images, downsample_scene(cached, 2).images)
    direct = render_scene(5, n_views=2, size=(16, 16))
    np.testing.assert_allclose(s.K, direct.K, rtol=1e-14)
    np.testing.assert_array_equal(s.world_from_cam, direct.world_from_cam)


def test_stale_capture_file_is_regenerated(tmp_path):
    ds = SyntheticScenes([3], n_views=2, size=(16, 16), cache_dir=tmp_path, kind="walk")
    good = ds[0]
    scene = load_scene(ds.path(3))
    bad_meta = dict(scene.meta, kind="turntable")            # version 1 expected, file says 3
    save_scene(ds.path(3), type(scene)(scene.images, scene.world_from_cam, scene.K, scene.depth, bad_meta))
    import io
    import json
    z = dict(np.load(ds.path(3)))
    z["meta"] = np.array(json.dumps(scene.meta))
    z["generator_version"] = np.array(2)                     # an older capture generator
    buf = io.BytesIO()
    np.savez(buf, **z)
    ds.path(3).write_bytes(buf.getvalue())
    with pytest.raises(InputError, match="generator version 2"):
        load_scene(ds.path(3))
    with pytest.warns(UserWarning, match="regenerating"):
        again = ds[0]
    _same(good, again)


def test_cli_pregenerates_capture_scenes(tmp_path, capsys):
    import json
    from iris_train.data import main
    main(["--kind", "walk=1,indoor=1", "--train", "2", "--size", "16", "16", "--render-size", "32", "32",
          "--views", "2", "--workers", "2", "--cache-dir", str(tmp_path)])
    out = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert out[0]["split"] == "train" and out[0]["generated"] == 2 and out[0]["bytes_per_scene"] > 0
    ds = SyntheticScenes([0, 1], n_views=2, size=(16, 16), cache_dir=tmp_path, kind="walk=1,indoor=1",
                         render_size=(32, 32))
    assert all(ds.is_cached(s) for s in (0, 1))
    assert sorted(p.parent.name for p in tmp_path.rglob("*.npz")) == sorted(ds.kind_of(s) for s in (0, 1))
    with pytest.raises(SystemExit):
        main(["--kind", "forest", "--train", "1"])

"""iris-eval --size S: renders at S x S scored against the photos brought to S, the references
encoded from their full-resolution photos, the "upsampled" baseline, the refusal of S above the
photos' size, and the default run left as it was."""
from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from iris_runtime.errors import InputError  # noqa: E402
from iris_train import build_model, preset, save_checkpoint  # noqa: E402
from iris_train.evaluate import (ORDERS, evaluate, load_scenes, main, nearest_reference,  # noqa: E402
                                 prepare_scene, split_frames)
from iris_train.metrics import capped_psnr, ssim  # noqa: E402

PAD = 16                 # columns added on each side: photos are H x (H + 2 PAD), not square


# The autouse fixture that holds torch to one thread for this module, as for test_evaluate's.
from .test_evaluate import one_torch_thread  # noqa: E402, F401


def rot_y(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def arc_poses(n=8):
    out = []
    for a in np.linspace(0, 40, n):
        T = np.eye(4)
        T[:3, :3] = rot_y(-a)
        T[:3, 3] = (0.6 * np.sin(np.radians(a)), 0.0, -0.6 * np.cos(np.radians(a)))
        out.append(T)
    return np.stack(out)


@functools.lru_cache(maxsize=None)
def square_scene(size: int):
    """A held-out synthetic scene rendered at size x size if the renderer works here, else random
    images on an arc (same interface)."""
    try:
        from iris_train.data import HELDOUT_SEEDS
        from iris_train.synthetic import render_scene
        s = render_scene(HELDOUT_SEEDS[0], n_views=8, size=(size, size))
        return s.images, s.world_from_cam, np.asarray(s.K, np.float64), s.depth
    except Exception:     # no EGL/pyrender
        rng = np.random.default_rng(5)
        f = 1.2 * size
        K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
        return (rng.integers(0, 256, (8, size, size, 3), dtype=np.uint8), arc_poses(), K,
                rng.uniform(0.2, 0.9, (8, size, size)).astype(np.float32))


def wide_scene(size: int):
    """``square_scene(size)`` with PAD random columns added on each side: photos size x (size +
    2 PAD), whose centre square is the render (K and depth padded alike)."""
    images, poses, K, depth = square_scene(size)
    rng = np.random.default_rng(11)
    wide = rng.integers(0, 256, (8, size, size + 2 * PAD, 3), dtype=np.uint8)
    wide[:, :, PAD:PAD + size] = images
    wide_depth = np.zeros((8, size, size + 2 * PAD), np.float32)
    wide_depth[:, :, PAD:PAD + size] = depth
    K = np.array(K)
    K[..., 0, 2] += PAD
    return SimpleNamespace(images=wide, world_from_cam=poses, K=K, depth=wide_depth)


def centre_square_area(photo, n):
    """Independent of iris_train/iris_runtime: the centre square of ``photo``, INTER_AREA to n."""
    h, w = photo.shape[:2]
    side = min(h, w)
    y0, x0 = (h - side) // 2, (w - side) // 2
    crop = np.ascontiguousarray(photo[y0:y0 + side, x0:x0 + side])
    return crop if side == n else cv2.resize(crop, (n, n), interpolation=cv2.INTER_AREA)


def tiny_model(name="tiny-rgb", size=16):
    torch.manual_seed(0)
    cfg = dataclasses.replace(preset(name), image_height=size, image_width=size, samples=8)
    model = build_model(cfg).eval()
    if cfg.explicit_rgb:          # the residual head starts at zero: let the field show
        with torch.no_grad():
            for p in model.renderer.rgb_head[-1].parameters():
                p.normal_(0.0, 0.2)
    return model


def scores(preds, gts):
    return {"psnr": float(np.mean([capped_psnr(p, g) for p, g in zip(preds, gts)])),
            "ssim": float(np.mean([ssim(p, g) for p, g in zip(preds, gts)]))}


# ----------------------------------------------------------------------------------------------
# Ground truth at S, and the refusal of S above the photos
# ----------------------------------------------------------------------------------------------

def test_ground_truth_at_the_output_size_is_a_centre_crop_and_inter_area():
    scene = wide_scene(48)
    p = prepare_scene(scene, 8, (16, 16), output_size=(40, 40))
    assert p.output_size == (40, 40) and p.gt_images.shape == (8, 40, 40, 3)
    expected = np.stack([centre_square_area(im, 40) for im in scene.images]) / 255.0
    np.testing.assert_array_equal(p.gt_images, expected)
    # The model's images: the same photos fitted to the model (what IrisRuntime.encode sees).
    np.testing.assert_array_equal(p.images, np.stack([centre_square_area(im, 16)
                                                      for im in scene.images]))
    assert [ph.shape for ph in p.photos] == [scene.images.shape[1:]] * 8     # full resolution
    # The true depth: the same crop, nearest neighbour (every value one of the stored depths).
    assert p.true_depth.shape == (8, 40, 40)
    assert np.isin(p.true_depth[0], scene.depth[0, :, PAD:PAD + 48]).all()
    # At the photos' own size the crop alone.
    same = prepare_scene(scene, 8, (16, 16), output_size=(48, 48))
    np.testing.assert_array_equal(same.gt_images * 255.0, scene.images[:, :, PAD:PAD + 48])


def test_output_size_above_the_photos_is_refused(tmp_path, capsys):
    scene = wide_scene(48)        # photos 80 wide, 48 high: 48 after the centre crop
    with pytest.raises(InputError, match=r"photos are 80x48 .*output size 49x49.*--size 48 or less"):
        prepare_scene(scene, 8, (16, 16), output_size=(49, 49))
    # A synthetic set: refused from its photo size before anything is rendered.
    with pytest.raises(InputError, match=r"synthetic:heldout.*photos are 256x256.*512x512"):
        load_scenes("synthetic:heldout", (64, 64), output_size=(512, 512))
    # The CLI on a folder of photos: one line, exit 2, naming the photos' size and S.
    from PIL import Image
    folder = tmp_path / "data" / "scene_a"
    folder.mkdir(parents=True)
    for k, im in enumerate(scene.images):
        Image.fromarray(im).save(folder / f"{k:03d}.png")
    ckpt = tmp_path / "model.pt"
    save_checkpoint(ckpt, tiny_model())
    assert main([str(ckpt), str(tmp_path / "data"), "--size", "64", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "80x48" in err and "64x64" in err
    assert main([str(ckpt), "synthetic:heldout", "--size", "300", "--no-progress"]) == 2
    assert "256x256" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# The exported model: the JSON, "upsampled" and the renders at S, recomputed independently
# ----------------------------------------------------------------------------------------------

def test_size_through_the_runtime_matches_an_independent_computation(model_dir):
    """Photos 80 high and 112 wide, S = 72 (a crop and a shrink), renders with the "balanced"
    preset (passed through; single-scale, as exact but half the samples: a random model's exact
    renders take minutes on a busy machine)."""
    from iris_runtime import IrisRuntime
    rt = IrisRuntime(model_dir, threads=1)
    H, W = rt.image_size
    N, knobs = 72, {"quality": "balanced"}
    scene = wide_scene(80)
    results = evaluate(rt, [scene], progress=False, size=N, **knobs)
    for R in results.values():
        assert R["output_size"] == [N, N] and R["model_size"] == [H, W]
        assert set(R["baselines"]) == {"upsampled", "best_reference", "nearest_reference",
                                       "mean_colour", "identity_poses"}
        for name in ("upsampled", "best_reference", "nearest_reference"):
            assert set(R["baselines"][name]) == {"psnr", "ssim"}
            assert set(R["scenes"][0]["baselines"][name]) >= {"psnr", "ssim"}
        assert R["model"]["depth_spearman"] is not None
    assert rt.default_cameras == "model"        # the random export: no solve to repeat below

    # Seq order, step by step with the public API: the reference photos at full resolution to
    # encode, the targets located from their photos fitted to the model.
    refs, targets = split_frames(8)
    encoded = rt.encode([scene.images[r] for r in refs])
    poses = rt.locate(encoded, [centre_square_area(scene.images[t], H) for t in targets])
    gt = {f: centre_square_area(scene.images[f], N) / 255.0 for f in range(8)}
    renders, upsampled = [], []
    for pose in poses:      # float64, as evaluate scores renders
        big = rt.render(encoded, pose, height=N, width=N, depth=True, **knobs).image_float
        renders.append(np.clip(np.asarray(big, np.float64), 0, 1))
        small = rt.render(encoded, pose, height=H, width=W, depth=True, **knobs).image_float
        small = np.clip(np.asarray(small, np.float64), 0, 1)
        upsampled.append(np.clip(cv2.resize(small, (N, N), interpolation=cv2.INTER_CUBIC), 0, 1))
    truth = [gt[t] for t in targets]
    record = results["seq"]["scenes"][0]
    for key, preds in (("upsampled", upsampled),):
        want = scores(preds, truth)
        assert record["baselines"][key]["psnr"] == pytest.approx(want["psnr"], abs=1e-9)
        assert record["baselines"][key]["ssim"] == pytest.approx(want["ssim"], abs=1e-9)
    want = scores(renders, truth)
    assert record["model"]["psnr"] == pytest.approx(want["psnr"], abs=1e-9)
    assert record["model"]["ssim"] == pytest.approx(want["ssim"], abs=1e-9)
    # The photo baselines at N: the same definitions (best by PSNR knowing the target; nearest
    # by the true cameras).
    best = [max(refs, key=lambda r: (capped_psnr(gt[r], gt[t]), -r)) for t in targets]
    assert record["baselines"]["best_reference"]["frames"] == best
    want = scores([gt[r] for r in best], truth)
    assert record["baselines"]["best_reference"]["psnr"] == pytest.approx(want["psnr"], abs=1e-12)
    near = nearest_reference(scene.world_from_cam, refs, targets)
    assert record["baselines"]["nearest_reference"]["frames"] == near
    want = scores([gt[r] for r in near], truth)
    assert record["baselines"]["nearest_reference"]["ssim"] == pytest.approx(want["ssim"], abs=1e-12)


class RecordingRuntime:
    """Duck-types IrisRuntime and records what every call was given; encodes and locates with
    the real runtime, renders a grey image of the size asked (the arguments are what count)."""

    def __init__(self, rt):
        self.rt, self.calls = rt, []
        self.image_size, self.near, self.far = rt.image_size, rt.near, rt.far
        self.unit_range = rt.unit_range
        self.default_cameras = rt.default_cameras

    def encode(self, images, **kw):
        self.calls.append(("encode", [np.asarray(i).shape for i in images], kw))
        return self.rt.encode(images, **kw)

    def locate(self, scene, images, **kw):
        self.calls.append(("locate", [np.asarray(i).shape for i in images], kw))
        return self.rt.locate(scene, images, **kw)

    def render(self, scene, pose, **kw):
        self.calls.append(("render", None, kw))
        shape = (kw["height"], kw["width"])
        return SimpleNamespace(image_float=np.full((*shape, 3), 0.5), depth=np.full(shape, 0.5))


def test_without_size_the_calls_and_the_json_are_as_before(model_dir):
    """The default run: the model's images to encode and locate, renders at the model's size
    with exactly the old arguments, no new JSON keys; --quality is passed through."""
    from iris_runtime import IrisRuntime
    rt = RecordingRuntime(IrisRuntime(model_dir, threads=1))
    H, W = rt.image_size
    scene = wide_scene(80)
    results = evaluate(rt, [scene], progress=False)
    assert {k for R in results.values() for k in R} == {"model", "baselines", "scenes"}
    assert "upsampled" not in results["seq"]["baselines"]
    assert all(shape == (H, W, 3) for name, shapes, _ in rt.calls if name != "render"
               for shape in shapes)
    assert [kw for name, _, kw in rt.calls if name == "render"] == \
        [{"height": H, "width": W, "depth": True}] * 6

    rt.calls.clear()
    sized = evaluate(rt, [scene], progress=False, size=72, quality="fast")
    encodes = [shapes for name, shapes, _ in rt.calls if name == "encode"]
    assert encodes == [[scene.images.shape[1:]] * 5] * 2            # full-resolution photos
    assert all(shape == (H, W, 3) for name, shapes, _ in rt.calls if name == "locate"
               for shape in shapes)
    # Per order: the targets at 72, then at the model's size for "upsampled".
    at_n = {"height": 72, "width": 72, "depth": True, "quality": "fast"}
    at_model = {"height": H, "width": W, "depth": True, "quality": "fast"}
    assert [kw for name, _, kw in rt.calls if name == "render"] == \
        ([at_n] * 3 + [at_model] * 3) * 2
    assert set(sized["rand"]["baselines"]) >= {"upsampled"}


# ----------------------------------------------------------------------------------------------
# The checkpoint backend
# ----------------------------------------------------------------------------------------------

def test_size_with_a_checkpoint_samples_colours_from_the_photos(tmp_path):
    from iris_train.evaluate import TorchBackend
    model = tiny_model()
    scene = wide_scene(48)
    backend = TorchBackend(model)
    encoded = backend.encode([scene.images[r] for r in (0, 2, 3)], colour_size=(40, 40))
    assert tuple(encoded.images.shape) == (3, 3, 40, 40)
    np.testing.assert_allclose(encoded.images[1].permute(1, 2, 0).numpy() * 255.0,
                               centre_square_area(scene.images[2], 40), atol=1e-4)
    results = evaluate(model, [scene], progress=False, size=40)
    for R in results.values():
        assert R["output_size"] == [40, 40] and R["model_size"] == [16, 16]
        assert R["baselines"]["upsampled"]["psnr"] is not None
    with pytest.raises(InputError, match="quality: 'fast'.*iris-export"):
        evaluate(model, [scene], progress=False, size=40, quality="fast")
    # The CLI on a folder, with a grid at S.
    from PIL import Image
    folder = tmp_path / "data" / "scene_a"
    folder.mkdir(parents=True)
    for k, im in enumerate(scene.images):
        Image.fromarray(im).save(folder / f"{k:03d}.png")
    ckpt, out = tmp_path / "model.pt", tmp_path / "eval.json"
    save_checkpoint(ckpt, model)
    assert main([str(ckpt), str(tmp_path / "data"), "--size", "32", "--json", str(out),
                 "--grid", str(tmp_path / "grid.png"), "--no-progress"]) == 0
    written = json.loads(Path(out).read_text())
    assert written["seq"]["output_size"] == [32, 32]
    assert written["seq"]["baselines"]["nearest_reference"] == {"psnr": None, "ssim": None}
    assert written["seq"]["scenes"][0]["baselines"]["upsampled"]["psnr"] > 0
    assert (tmp_path / "grid.png").read_bytes()[:4] == b"\x89PNG"
    for order in ORDERS:
        assert set(written[order]["baselines"]) == {"upsampled", "best_reference",
                                                    "nearest_reference", "mean_colour",
                                                    "identity_poses"}

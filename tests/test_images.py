"""iris_runtime.images: loading anything image-like, and the documented crop/resize."""
from __future__ import annotations

import io

import cv2
import numpy as np
import pytest
from PIL import Image

from iris_runtime.errors import ImageError, IrisError
from iris_runtime.images import fit_to_model, load_image, plan_crop_resize


def _rgb(h=6, w=5, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


# ---------------------------------------------------------------------------------------------
# arrays and PIL images
# ---------------------------------------------------------------------------------------------

def test_uint8_rgb_passes_through():
    a = _rgb()
    out = load_image(a)
    assert out.dtype == np.uint8 and out.shape == (6, 5, 3)
    np.testing.assert_array_equal(out, a)


def test_grayscale_and_single_channel_are_repeated():
    g = _rgb()[:, :, 0]
    for x in (g, g[:, :, None]):
        out = load_image(x)
        assert out.shape == (6, 5, 3)
        for c in range(3):
            np.testing.assert_array_equal(out[:, :, c], g)


def test_rgba_drops_alpha():
    a = np.dstack([_rgb(), np.zeros((6, 5), np.uint8)])
    np.testing.assert_array_equal(load_image(a), a[:, :, :3])


def test_uint16_is_scaled_by_257_with_rounding():
    a = np.array([[0, 257, 128, 129, 65535, 257 * 200 + 128]], np.uint16)
    out = load_image(a)[0, :, 0]
    np.testing.assert_array_equal(out, [0, 1, 0, 1, 255, 200])
    np.testing.assert_array_equal(out, np.rint(a[0] / 257.0).astype(np.uint8))


def test_float_is_scaled_and_rounded_and_only_rounding_excess_clipped():
    a = np.array([[-1e-7, 0.0, 0.2, 0.5, 1.0, 1.0 + 5e-7]], np.float64)
    out = load_image(a)[0, :, 1]
    np.testing.assert_array_equal(out, [0, 0, 51, 128, 255, 255])
    one = np.nextafter(np.float32(1), np.float32(2))              # float32 rounding above 1
    assert load_image(np.full((2, 2, 3), one, np.float32))[0, 0, 0] == 255


@pytest.mark.parametrize("values, fix", [
    ([0.0, 17.0, 255.0], "divide by 255"),                        # the common mistake
    ([0.0, 3.0], "divide by 255"),
    ([0.0, 1000.0, 65535.0], "divide by 65535"),
    ([-1.0, 0.0, 1.0], r"(image + 1) / 2"),
    ([0.0, 1.2], "np.clip(image, 0, 1)"),                         # an interpolation overshoot
    ([-1e-3, 0.5], "np.clip(image, 0, 1)"),
    ([0.0, 1.0 + 2e-6], "np.clip(image, 0, 1)"),                  # beyond FLOAT_IMAGE_ATOL
])
def test_float_outside_0_1_raises_image_error_saying_how_to_fix(values, fix):
    """Float images outside [0, 1] beyond rounding used to be clipped silently (0..255 rendered
    white); now ``ImageError`` naming the argument, the range found and the fix."""
    a = np.resize(np.array(values, np.float32), (4, 5, 3))
    for x in (a, a.astype(np.float64), a.reshape(4, 15)):          # RGB and grayscale
        with pytest.raises(ImageError) as e:
            load_image(x, name="images[2]")
        msg = str(e.value)
        assert msg.startswith("images[2]: ") and "[0, 1]" in msg and fix in msg, msg
        assert isinstance(e.value, IrisError) and isinstance(e.value, ValueError)


def test_float_pil_images_and_files_follow_the_float_rule(tmp_path):
    """PIL mode "F" (e.g. a float32 TIFF): values in [0, 1] are scaled, 0..255 raise."""
    ok = np.array([[0.0, 0.2, 1.0]], np.float32)
    np.testing.assert_array_equal(load_image(Image.fromarray(ok))[0, :, 2], [0, 51, 255])
    bad = ok * 255
    with pytest.raises(ImageError, match="divide by 255"):
        load_image(Image.fromarray(bad))
    Image.fromarray(bad).save(tmp_path / "f.tiff")
    with pytest.raises(ImageError, match="divide by 255") as e:
        load_image(tmp_path / "f.tiff", name="images[0]")
    assert "images[0]" in str(e.value) and "f.tiff" in str(e.value)


@pytest.mark.parametrize("bad", [
    np.zeros((0, 5, 3), np.uint8), np.zeros((4, 0), np.uint8),          # empty
    np.zeros((4, 5, 2), np.uint8), np.zeros((2, 4, 5, 3), np.uint8),    # wrong shape
    np.zeros((4, 5, 3), np.int32), np.zeros((4, 5), bool),              # wrong dtype
    np.full((4, 5, 3), np.nan, np.float32),                             # NaN
])
def test_bad_arrays_raise_image_error(bad):
    with pytest.raises(ImageError) as e:
        load_image(bad, name="images[3]")
    assert "images[3]" in str(e.value)
    assert isinstance(e.value, IrisError) and isinstance(e.value, ValueError)


def test_unsupported_type_raises():
    with pytest.raises(ImageError, match="file path, a PIL image or a numpy array"):
        load_image([[1, 2, 3]])


@pytest.mark.parametrize("mode", ["RGB", "L", "RGBA", "P", "LA", "CMYK", "1"])
def test_pil_modes(mode):
    base = Image.fromarray(_rgb(8, 7))
    img = base.convert(mode)
    out = load_image(img)
    assert out.shape == (8, 7, 3) and out.dtype == np.uint8
    if mode == "RGB":
        np.testing.assert_array_equal(out, np.asarray(base))
    if mode == "L":
        np.testing.assert_array_equal(out[:, :, 2], np.asarray(img))


def test_pil_16bit_grayscale():
    a = np.array([[0, 257, 65535]], np.uint16)
    img = Image.fromarray(a)          # mode I;16
    np.testing.assert_array_equal(load_image(img)[0, :, 0], [0, 1, 255])


def test_pil_palette_cmyk_and_la_convert_like_pil():
    """P, CMYK, 1 (and the rest): Pillow's own ``convert("RGB")``; LA: its L channel, alpha dropped."""
    base = Image.fromarray(_rgb(8, 7, seed=5))
    for mode in ("P", "CMYK", "1", "YCbCr"):
        img = base.convert(mode)
        np.testing.assert_array_equal(load_image(img), np.asarray(img.convert("RGB")))
    la = base.convert("LA")
    out = load_image(la)
    for c in range(3):
        np.testing.assert_array_equal(out[:, :, c], np.asarray(la)[:, :, 0])


def test_pil_32bit_integer_images():
    """Mode "I" (how Pillow may open 16-bit PNGs): 0..65535 follow the uint16 rule, else refused."""
    a = np.array([[0, 257, 65535]], np.int32)
    img = Image.fromarray(a)
    assert img.mode == "I"
    np.testing.assert_array_equal(load_image(img)[0, :, 0], [0, 1, 255])
    with pytest.raises(ImageError, match="0..65535"):
        load_image(Image.fromarray(np.array([[0, 70000]], np.int32)))
    with pytest.raises(ImageError, match="0..65535"):
        load_image(Image.fromarray(np.array([[-1, 5]], np.int32)))


# ---------------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------------

def test_png_jpeg_files(tmp_path):
    a = _rgb(10, 12)
    Image.fromarray(a).save(tmp_path / "a.png")
    np.testing.assert_array_equal(load_image(tmp_path / "a.png"), a)
    np.testing.assert_array_equal(load_image(str(tmp_path / "a.png")), a)
    smooth = np.full((16, 16, 3), 120, np.uint8)
    Image.fromarray(smooth).save(tmp_path / "b.jpg", quality=95)
    out = load_image(tmp_path / "b.jpg")
    assert out.shape == (16, 16, 3) and np.abs(out.astype(int) - 120).max() <= 2


def test_grayscale_rgba_and_16bit_png_files(tmp_path):
    g = _rgb(5, 4)[:, :, 0]
    Image.fromarray(g).save(tmp_path / "g.png")
    np.testing.assert_array_equal(load_image(tmp_path / "g.png")[:, :, 1], g)

    rgba = np.dstack([_rgb(5, 4), np.full((5, 4), 7, np.uint8)])
    Image.fromarray(rgba).save(tmp_path / "rgba.png")
    np.testing.assert_array_equal(load_image(tmp_path / "rgba.png"), rgba[:, :, :3])

    g16 = np.array([[0, 257, 1000, 65535]], np.uint16)
    cv2.imwrite(str(tmp_path / "g16.png"), g16)
    np.testing.assert_array_equal(load_image(tmp_path / "g16.png")[0, :, 0],
                                  np.rint(g16[0] / 257).astype(np.uint8))

    # 16-bit colour: Pillow alone would truncate to the high byte; we keep round(x / 257).
    c16 = np.random.default_rng(1).integers(0, 65536, (3, 4, 3)).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "c16.png"), c16[:, :, ::-1])        # OpenCV writes BGR
    np.testing.assert_array_equal(load_image(tmp_path / "c16.png"),
                                  np.rint(c16 / 257.0).astype(np.uint8))


def test_16bit_rgba_png_file_drops_alpha_at_full_depth(tmp_path):
    c16 = np.random.default_rng(2).integers(0, 65536, (3, 4, 4)).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "c16a.png"), c16[:, :, [2, 1, 0, 3]])    # OpenCV writes BGRA
    np.testing.assert_array_equal(load_image(tmp_path / "c16a.png"),
                                  np.rint(c16[:, :, :3] / 257.0).astype(np.uint8))


def test_broken_exif_block_keeps_the_image(tmp_path, monkeypatch):
    """A decodable image whose EXIF cannot be applied loads without the orientation step."""
    import iris_runtime.images as images
    a = _rgb(4, 6, seed=6)
    Image.fromarray(a).save(tmp_path / "a.png")

    def broken(img):
        raise SyntaxError("corrupt EXIF")
    monkeypatch.setattr(images.ImageOps, "exif_transpose", broken)
    np.testing.assert_array_equal(load_image(tmp_path / "a.png"), a)


def test_exif_orientation_is_applied(tmp_path):
    a = np.zeros((4, 8, 3), np.uint8)
    a[:, :4] = 255                     # left half white
    img = Image.fromarray(a)
    exif = img.getexif()
    exif[0x0112] = 6                   # "rotate 90 CW to display"
    img.save(tmp_path / "rot.jpg", exif=exif, quality=100)
    out = load_image(tmp_path / "rot.jpg")
    assert out.shape == (8, 4, 3)      # displayed upright: portrait
    assert out[:3].mean() > 200 and out[5:].mean() < 50      # left half -> top after 90 CW


def test_bad_files_raise_image_error_naming_the_file(tmp_path):
    good = io.BytesIO()
    Image.fromarray(_rgb(64, 64)).save(good, format="PNG")
    data = good.getvalue()
    cases = {
        "truncated.png": data[: len(data) // 2],
        "garbage.png": bytes(range(256)) * 4,
        "empty.jpg": b"",
        "notes.txt": b"hello, not an image\n",
    }
    for name, content in cases.items():
        p = tmp_path / name
        p.write_bytes(content)
        with pytest.raises(ImageError) as e:
            load_image(p)
        assert name in str(e.value), str(e.value)
    with pytest.raises(ImageError, match="no such file"):
        load_image(tmp_path / "missing.png")
    with pytest.raises(ImageError, match="directory"):
        load_image(tmp_path)


# ---------------------------------------------------------------------------------------------
# crop and resize
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("src,dst,box", [
    ((100, 200), (64, 64), (50, 0, 100, 100)),       # wide: keep height, crop width centred
    ((300, 100), (64, 64), (0, 100, 100, 100)),      # tall: keep width
    ((64, 64), (64, 64), (0, 0, 64, 64)),            # already right
    ((30, 40), (60, 80), (0, 0, 40, 30)),            # same aspect, enlarged
    ((101, 201), (64, 64), (50, 0, 101, 101)),       # odd sizes: offsets floor
    ((480, 640), (64, 96), (0, 26, 640, 427)),       # 4:3 photo to 3:2 model: (480-427)//2
])
def test_crop_box(src, dst, box):
    plan = plan_crop_resize(*src, *dst)
    assert (plan.x0, plan.y0, plan.crop_w, plan.crop_h) == box
    img = _rgb(*src)
    out, plan2 = fit_to_model(img, *dst)
    assert out.shape == (*dst, 3) and out.dtype == np.uint8 and plan2 == plan


def test_shrink_uses_area_and_enlarge_uses_linear():
    img = _rgb(128, 256, seed=3)
    out, plan = fit_to_model(img, 64, 64)
    crop = img[:, 64:192]
    np.testing.assert_array_equal(out, cv2.resize(crop, (64, 64), interpolation=cv2.INTER_AREA))
    small = _rgb(16, 16, seed=4)
    out, _ = fit_to_model(small, 64, 64)
    np.testing.assert_array_equal(out, cv2.resize(small, (64, 64), interpolation=cv2.INTER_LINEAR))


def test_adjusted_intrinsics_predict_projections_exactly():
    rng = np.random.default_rng(0)
    for src, dst in [((480, 640), (64, 64)), ((300, 200), (64, 96)), ((50, 70), (64, 64)),
                     ((1080, 1920), (48, 64))]:
        plan = plan_crop_resize(*src, *dst)
        K = np.array([[rng.uniform(300, 900), 0.0, src[1] / 2 + rng.normal(0, 5)],
                      [0.0, rng.uniform(300, 900), src[0] / 2 + rng.normal(0, 5)], [0, 0, 1.0]])
        X = rng.normal(0, 1, (50, 3)) + [0, 0, 5]               # points in front of the camera
        p = (K @ X.T).T
        uv_src = p[:, :2] / p[:, 2:]
        uv_pred = plan.to_output(uv_src)                         # where crop + resize moves them
        Ka = plan.adjust_intrinsics(K)
        q = (Ka @ X.T).T
        np.testing.assert_allclose(q[:, :2] / q[:, 2:], uv_pred, atol=1e-9, rtol=0)
        np.testing.assert_allclose(plan.to_source(uv_pred), uv_src, atol=1e-9, rtol=0)


def test_crop_resize_moves_image_content_where_the_plan_says():
    """A blurred dot at a sub-pixel position ends up where ``to_output`` predicts (pixel centres at +0.5)."""
    H, W = 300, 500
    u0, v0 = 287.3, 141.8                  # continuous (u, v), pixel centres at j + 0.5
    j, i = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    blob = np.exp(-((j - u0) ** 2 + (i - v0) ** 2) / (2 * 6.0 ** 2))
    img = np.repeat((blob / blob.max() * 255).round().astype(np.uint8)[:, :, None], 3, axis=2)
    out, plan = fit_to_model(img, 64, 64)
    w = out[:, :, 0].astype(np.float64)
    jj, ii = np.meshgrid(np.arange(64) + 0.5, np.arange(64) + 0.5)
    centroid = np.array([(w * jj).sum() / w.sum(), (w * ii).sum() / w.sum()])
    np.testing.assert_allclose(centroid, plan.to_output(np.array([u0, v0])), atol=0.05)


def test_fit_to_model_rejects_non_uint8():
    with pytest.raises(ImageError, match="uint8"):
        fit_to_model(np.zeros((4, 4, 3), np.float32), 8, 8)
    with pytest.raises(ImageError, match="height"):
        fit_to_model(np.zeros((4, 4, 3), np.uint8), 0, 8)

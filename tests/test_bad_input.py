"""Bad input at every public entry -> one typed error, never a raw numpy/onnxruntime traceback.

Entries: ``IrisRuntime(...)``, ``encode``, ``render``, ``locate``, ``Scene``, ``iris-render``, ``iris-export``
(``export_model``), and the data loading of ``iris-train`` / ``iris-eval``. Every error must be an
``IrisError`` (the project's one base class) and also a ``ValueError`` (bad argument) or an
``OSError`` (bad model file), name the argument or file, and leave nothing half-written.
Cases already covered elsewhere are not repeated here: tests/test_runtime.py (pose shapes, NaN,
mirrored / singular / non-orthonormal poses, tampered graph, manifest version and '..' paths,
symlinks), tests/test_images.py (array and file conversions), tests/test_export.py (bad
checkpoints, existing OUT_DIR), tests/test_data.py (folder errors).

Grayscale, RGBA and 16-bit images are *converted*, not rejected: checked end to end here.
"""
from __future__ import annotations

import io
import json
import shutil
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from iris_runtime import (ImageError, InputError, IrisError, IrisRuntime, ManifestError,
                          ModelFileError, ModelIntegrityError, Scene)
from iris_runtime import runtime as R
from iris_runtime.cli import main as render_main
from iris_runtime.manifest import external_data_locations


@pytest.fixture(scope="module")
def rt(any_model_dir) -> IrisRuntime:
    """The tests of encode/render/locate/Scene input run on both test models (conftest
    ``any_model_dir``: the random tiny model and its explicit-colour twin)."""
    return IrisRuntime(any_model_dir, threads=1)


@pytest.fixture(scope="module")
def scene(rt) -> Scene:
    rng = np.random.default_rng(0)
    return rt.encode([rng.integers(0, 256, (*rt.image_size, 3), dtype=np.uint8) for _ in range(2)])


@pytest.fixture
def model_copy(model_dir, tmp_path) -> Path:
    out = tmp_path / "model"
    shutil.copytree(model_dir, out)
    return out


def assert_typed(info, kind=ValueError, *names):
    """The raised error is an IrisError and a ``kind``, one readable line naming ``names``."""
    exc = info.value
    assert isinstance(exc, IrisError) and isinstance(exc, kind), type(exc).__mro__
    text = str(exc)
    assert text and "Traceback" not in text
    for name in names:
        assert name in text, (name, text)


def _png_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG")
    return buf.getvalue()


# ----------------------------------------------------------------------------------------------
# IrisRuntime(...)
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, name", [
    ({"threads": "2"}, "threads"), ({"threads": 1.5}, "threads"), ({"threads": -3}, "threads"),
    ({"threads": True}, "threads"), ({"precision": ["float32"]}, "precision"),
    ({"precision": None}, "precision"),
])
def test_runtime_arguments(model_dir, kwargs, name):
    with pytest.raises(InputError) as info:
        IrisRuntime(model_dir, **kwargs)
    assert_typed(info, ValueError, name)


@pytest.mark.parametrize("arg", [None, 42, ["a"]])
def test_model_dir_of_wrong_type(arg):
    with pytest.raises(InputError) as info:
        IrisRuntime(arg)
    assert_typed(info, ValueError, "model_dir")


def test_model_dir_is_a_file(tmp_path):
    f = tmp_path / "iris.json"
    f.write_text("{}")
    with pytest.raises(ModelFileError) as info:
        IrisRuntime(f)
    assert_typed(info, OSError, "no such directory")


def _edit_manifest(d: Path, edit) -> None:
    doc = json.loads((d / "iris.json").read_text())
    edit(doc)
    (d / "iris.json").write_text(json.dumps(doc))


@pytest.mark.parametrize("edit, error, match", [
    (lambda d: d.update(version="1"), ModelFileError, "version"),
    (lambda d: d.update(version=True), ModelFileError, "version"),
    (lambda d: d.update(version=None), ModelFileError, "version"),
    (lambda d: d.update(version=1), ModelFileError, "re-export with iris-export"),
    (lambda d: d.update(version=99), ModelFileError, "re-export with iris-export"),
    (lambda d: d["graphs"]["encoder"]["inputs"].pop("is_reference"), ManifestError, "is_reference"),
    (lambda d: d.update(samples=0), ManifestError, "samples"),
    (lambda d: d.update(far=float("nan")) or d, ManifestError, "far"),
    (lambda d: d.update(image_size=[64]), ManifestError, "image_size"),
    (lambda d: d["graphs"]["renderer"].update(file="C:\\model\\renderer.onnx"), ManifestError,
     "relative"),
    (lambda d: d["graphs"]["renderer"].update(file=None), ManifestError, "file"),
    (lambda d: d.update(graphs=[]), ManifestError, "graphs"),
    (lambda d: d.update(cameras="colmap"), ManifestError, "cameras"),
    (lambda d: d["config"].update(blend_angle=-1.0), ManifestError, "blend_angle"),
    (lambda d: d["config"].update(blend_angle="wide"), ManifestError, "blend_angle"),
])
def test_manifest_fields(model_copy, edit, error, match):
    _edit_manifest(model_copy, edit)
    with pytest.raises(error) as info:
        IrisRuntime(model_copy)
    assert_typed(info, OSError, match)


def test_manifest_not_an_object_and_not_utf8(model_copy):
    (model_copy / "iris.json").write_text("[1, 2]")
    with pytest.raises(ManifestError) as info:
        IrisRuntime(model_copy)
    assert_typed(info, OSError, "iris.json")
    (model_copy / "iris.json").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ManifestError) as info:
        IrisRuntime(model_copy)
    assert_typed(info, OSError, "iris.json")


def test_truncated_graph(model_copy):
    path = model_copy / "encoder.onnx"
    path.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(ModelIntegrityError) as info:
        IrisRuntime(model_copy)
    assert_typed(info, OSError, "encoder", "sha256")


def _graph_with_external_data(location: str) -> bytes:
    """A tiny valid ONNX model whose one initializer lives in external data at ``location``."""
    pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper
    w = numpy_helper.from_array(np.ones(4, np.float32), "w")
    w.data_location = TensorProto.EXTERNAL
    for k, v in (("location", location), ("offset", "0"), ("length", "16")):
        entry = w.external_data.add()
        entry.key, entry.value = k, v
    graph = helper.make_graph([helper.make_node("Add", ["x", "w"], ["y"])], "g",
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, [4])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [4])],
                              initializer=[w])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 9
    return model.SerializeToString()


@pytest.mark.parametrize("location, error, match", [
    ("../secret.bin", ManifestError, "outside the model directory"),
    ("/etc/passwd", ManifestError, "outside the model directory"),
    ("weights.bin", ModelFileError, "self-contained"),
])
def test_external_data_outside_the_model_dir(model_copy, tmp_path, location, error, match):
    """A graph (re-hashed into the manifest, so the sha256 check passes) whose tensors point at
    external data is refused at construction, before onnxruntime reads anything."""
    import hashlib
    data = _graph_with_external_data(location)
    assert external_data_locations(data) == [location]
    (tmp_path / "secret.bin").write_bytes(np.arange(4, dtype=np.float32).tobytes())
    (model_copy / "weights.bin").write_bytes(np.arange(4, dtype=np.float32).tobytes())
    (model_copy / "renderer.onnx").write_bytes(data)
    _edit_manifest(model_copy, lambda d: d["graphs"]["renderer"].update(
        sha256=hashlib.sha256(data).hexdigest()))
    with pytest.raises(error) as info:
        IrisRuntime(model_copy)
    assert_typed(info, OSError, match, "renderer")


def test_exported_graphs_are_self_contained(model_dir):
    for name in ("encoder.onnx", "renderer.onnx"):
        assert external_data_locations((Path(model_dir) / name).read_bytes()) == []
    assert external_data_locations(b"\xff\xff\xff not protobuf") is None


# ----------------------------------------------------------------------------------------------
# encode
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("images, error, name", [
    ([np.zeros((0, 64, 3), np.uint8)], ImageError, "images[0]"),
    ([np.zeros((64, 0, 3), np.uint8)], ImageError, "images[0]"),
    ([np.zeros((64,), np.uint8)], ImageError, "images[0]"),
    ([np.zeros((2, 64, 64, 3), np.uint8)], ImageError, "images[0]"),
    ([np.zeros((8, 8, 3), bool)], ImageError, "dtype"),
    ([np.zeros((8, 8, 3), np.complex64)], ImageError, "dtype"),
    ([np.zeros((8, 8, 3), object)], ImageError, "dtype"),
    ([np.full((8, 8, 3), np.inf, np.float32)], ImageError, "NaN or inf"),
    ([np.zeros((8, 8, 3), np.uint8), None], ImageError, "images[1]"),
    ([3.5], ImageError, "images[0]"),
    ((x for x in []), InputError, "at least one"),
    (None, InputError, "images"),
])
def test_encode_bad_images(rt, images, error, name):
    with pytest.raises(error) as info:
        rt.encode(images)
    assert_typed(info, ValueError, name)


@pytest.mark.parametrize("content, match", [
    (b"", "empty"),
    (b"this is not an image\n", "not a readable image"),
    ("truncated", "not a readable image"),
    (None, "is a directory"),
])
def test_encode_bad_files(rt, tmp_path, content, match):
    path = tmp_path / "photo.png"
    if content is None:
        path.mkdir()
    else:
        if content == "truncated":
            content = _png_bytes(np.full((32, 32, 3), 7, np.uint8))[:60]
        path.write_bytes(content)
    good = np.zeros((64, 64, 3), np.uint8)
    with pytest.raises(ImageError) as info:
        rt.encode([good, path])
    assert_typed(info, ValueError, "images[1]", "photo.png", match)


@pytest.mark.parametrize("scale, fix", [(255.0, "divide by 255"), (65535.0, "divide by 65535")])
def test_float_images_outside_0_1_raise_instead_of_rendering_white(rt, scene, scale, fix):
    """A float image of 0..255 values (a common mistake) was clipped to [0, 1] without a word and
    encoded as white; now encode and locate raise ImageError naming the argument and the fix."""
    rng = np.random.default_rng(4)
    good = rng.random((*rt.image_size, 3)).astype(np.float32)
    with pytest.raises(ImageError) as info:
        rt.encode([good, good * scale])
    assert_typed(info, ValueError, "images[1]", "[0, 1]", fix)
    with pytest.raises(ImageError) as info:
        rt.locate(scene, good * scale)
    assert_typed(info, ValueError, "image", fix)
    rt.encode([good, good + np.float32(5e-7)])          # a rounding excess is clipped, as before


def test_cli_float_image_file_outside_0_1_is_one_line_and_writes_nothing(model_dir, tmp_path,
                                                                          capsys):
    path = tmp_path / "float255.tiff"
    Image.fromarray(np.full((20, 24), 200.0, np.float32)).save(path)       # Pillow mode "F"
    out = tmp_path / "out"
    code, err = _cli(capsys, model_dir, path, "-o", out, "--view", 0)
    assert code == 2, err
    assert err.startswith("iris-render: error:") and len(err.strip().splitlines()) == 1, err
    assert "float255.tiff" in err and "divide by 255" in err
    assert not out.exists()


def test_grayscale_rgba_16bit_are_converted_not_rejected(rt, tmp_path):
    """Encoding grayscale / RGBA / 16-bit inputs (arrays and files) equals encoding the RGB
    images they are converted to (images.py rules: repeat, drop alpha, round(x / 257))."""
    import cv2
    rng = np.random.default_rng(3)
    gray = rng.integers(0, 256, (64, 64), dtype=np.uint8)
    rgba = rng.integers(0, 256, (64, 64, 4), dtype=np.uint8)
    deep = rng.integers(0, 65536, (64, 64, 3), dtype=np.uint16)
    Image.fromarray(gray).save(tmp_path / "gray.png")
    Image.fromarray(rgba).save(tmp_path / "rgba.png")
    assert cv2.imwrite(str(tmp_path / "deep.png"), deep[..., ::-1])        # 16-bit colour PNG
    expected = rt.encode([np.repeat(gray[..., None], 3, 2), rgba[..., :3],
                          ((deep.astype(np.uint32) * 2 + 257) // 514).astype(np.uint8)])
    for inputs in ([gray, rgba, deep], [tmp_path / "gray.png", tmp_path / "rgba.png",
                                        tmp_path / "deep.png"]):
        got = rt.encode(inputs)
        np.testing.assert_array_equal(got.field_maps, expected.field_maps)
        np.testing.assert_array_equal(got.world_from_cam, expected.world_from_cam)


def test_too_many_views_fail_before_allocating(rt):
    one = np.zeros((64, 64, 3), np.uint8)
    images = [one] * (rt.max_views + 1)
    tracemalloc.start()
    try:
        with pytest.raises(InputError) as info:
            rt.encode(images)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert_typed(info, ValueError, "images", str(rt.max_views), "MAX_ENCODER_TOKENS")
    assert peak < 1 << 20                    # nothing of the [V, 3, H, W] batch was allocated
    assert rt.max_views >= 32                # the documented minimum use (32 reference views)


# ----------------------------------------------------------------------------------------------
# render
# ----------------------------------------------------------------------------------------------

def _rigid(t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = t
    return T


@pytest.mark.parametrize("pose, match", [
    (np.full((4, 4), np.inf), "NaN or inf"),
    ([[1, 0, 0], [0, 1, 0, 0]], "4x4"),                      # ragged
    (None, "4x4"),
    (np.eye(4, dtype=np.complex128), "4x4"),
    (np.eye(4, dtype=bool), "4x4"),
    (np.eye(4)[None], "shape"),
    (np.diag([1.0, 1.0, 1.0 + 1e-3, 1.0]), "orthonormal"),     # scale error 1e-3 > 1e-4
    (2.5, "4x4"),
    (np.int64(7), "out of range"),
])
def test_render_bad_pose(rt, scene, pose, match):
    with pytest.raises(InputError) as info:
        rt.render(scene, pose, height=2, width=2)
    assert_typed(info, ValueError, "pose", match)


def test_render_accepts_nested_lists_and_float32(rt, scene):
    a = rt.render(scene, _rigid((0.01, 0, 0)).tolist(), height=2, width=2)
    b = rt.render(scene, _rigid((0.01, 0, 0)).astype(np.float32), height=2, width=2)
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("kwargs, name", [
    ({"height": "8"}, "height"), ({"width": -1}, "width"), ({"height": 8.0}, "height"),
    ({"height": True}, "height"),
    ({"intrinsics": [["a"] * 3] * 3}, "intrinsics"),
    ({"intrinsics": np.full((3, 3), np.nan)}, "intrinsics"),
    ({"intrinsics": [[4, 1, 2], [0, 4, 2], [0, 0, 1]]}, "intrinsics"),      # skew
    ({"intrinsics": [[0, 0, 2], [0, 4, 2], [0, 0, 1]]}, "intrinsics"),      # zero focal
    ({"chunk_rays": 2.0}, "chunk_rays"), ({"chunk_rays": "64"}, "chunk_rays"),
    ({"progress": "yes"}, "progress"),
    ({"sample": 32}, "sample"),                     # not a RenderSettings field: named, typed
])
def test_render_bad_arguments(rt, scene, kwargs, name):
    kwargs = {"height": 4, "width": 4, **kwargs}
    with pytest.raises(InputError) as info:
        rt.render(scene, 0, **kwargs)
    assert_typed(info, ValueError, name)


@pytest.mark.parametrize("kwargs", [
    {"height": 100_000, "width": 100_000},
    {"height": 100_000},                            # the other side follows the model's aspect
    {"height": R.MAX_OUTPUT_PIXELS + 1, "width": 1},
])
def test_render_of_absurd_size_fails_before_allocating(rt, scene, kwargs):
    tracemalloc.start()
    try:
        with pytest.raises(InputError) as info:
            rt.render(scene, 0, **kwargs)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert_typed(info, ValueError, "MAX_OUTPUT_PIXELS")
    assert peak < 1 << 20
    # The same check when the images are given: refused before the encoder runs.
    with pytest.raises(InputError, match="MAX_OUTPUT_PIXELS"):
        rt.render(["/nonexistent.png"], 0, **kwargs)


def test_render_with_a_huge_explicit_chunk_fails_before_allocating(rt, scene):
    with pytest.raises(InputError) as info:
        rt.render(scene, 0, height=512, width=512, chunk_rays=512 * 512)
    assert_typed(info, ValueError, "chunk_rays", "MAX_CHUNK_SAMPLES")
    # A chunk larger than the image is only as large as the image: accepted.
    assert rt.render(scene, 0, height=2, width=2, chunk_rays=10 ** 9).shape == (2, 2, 3)


# ----------------------------------------------------------------------------------------------
# Scene
# ----------------------------------------------------------------------------------------------

def _scene_kwargs(scene: Scene) -> dict:
    return dict(field_maps=scene.field_maps, world_from_cam=scene.world_from_cam,
                focal=scene.focal, K=scene.K, image_size=scene.image_size)


def _with(a, index, value):
    a = np.array(a, copy=True)
    a[index] = value
    return a


@pytest.mark.parametrize("field, make, match", [
    ("field_maps", lambda s: _with(s.field_maps, (0, 0, 0, 0), np.nan), "field_maps"),
    ("field_maps", lambda s: "maps", "field_maps"),
    ("world_from_cam", lambda s: _with(s.world_from_cam, (1, 0, 3), np.inf), "world_from_cam"),
    ("world_from_cam", lambda s: _with(s.world_from_cam, (1, 2, 2), -1.0), "world_from_cam[1]"),
    ("world_from_cam", lambda s: _with(s.world_from_cam, (1, slice(0, 3), slice(0, 3)), 0.0),
     "world_from_cam[1]"),
    ("focal", lambda s: np.array([0.0, 1.0]), "focal"),
    ("focal", lambda s: np.array([np.nan, 1.0]), "focal"),
    ("focal", lambda s: [None, None], "focal"),
    ("K", lambda s: np.eye(4), "K"),
    ("image_size", lambda s: (0, 64), "image_size"),
    ("reference_images", lambda s: np.zeros((2, 3, 8, 8), np.float32), "reference_images"),
    ("reference_images", lambda s: np.full((1, 3, *s.image_size), 2.0), "reference_images"),
    ("reference_images", lambda s: np.full((1, 3, *s.image_size), np.nan), "reference_images"),
    ("reference_images", lambda s: "images", "reference_images"),
])
def test_scene_rejects_bad_contents(scene, field, make, match):
    kwargs = _scene_kwargs(scene)
    kwargs[field] = make(scene)
    with pytest.raises(InputError) as info:
        Scene(**kwargs)
    assert_typed(info, ValueError, match)


@pytest.mark.parametrize("indices", [None, [0.5], [[0, 1]], "01", []])
def test_scene_subset_bad_indices(scene, indices):
    with pytest.raises(InputError) as info:
        scene.subset(indices)
    assert_typed(info, ValueError, "indices")


@pytest.mark.parametrize("args, error, match", [
    (lambda rt, s: (12, np.zeros((64, 64, 3), np.uint8)), InputError, "scene"),
    (lambda rt, s: (s, None), InputError, "image"),
    (lambda rt, s: (s, 3.5), InputError, "image"),
    (lambda rt, s: (s, []), InputError, "image"),
    (lambda rt, s: (s, "missing.png"), ImageError, "missing.png"),
    (lambda rt, s: (s, [np.zeros((64, 64, 3), np.uint8), np.zeros((0, 4, 3), np.uint8)]),
     ImageError, "image[1]"),
    (lambda rt, s: (s, np.zeros((64, 64, 5), np.uint8)), ImageError, "image"),
    (lambda rt, s: (s, [np.zeros((4, 4, 3), np.uint8)] * (R.MAX_LOCATE_CALLS * rt.max_views + 1)),
     InputError, "image"),
    (lambda rt, s: (Scene(**_scene_kwargs(s)), np.zeros((64, 64, 3), np.uint8)), InputError,
     "reference images"),
    (lambda rt, s: (Scene(**_scene_kwargs(s), model_id="0" * 64), np.zeros((64, 64, 3), np.uint8)),
     InputError, "another model"),
    (lambda rt, s: (Scene(**_scene_kwargs(s), model_id=s.model_id,
                          reference_images=1.0 - s.reference_images),
                    np.zeros((64, 64, 3), np.uint8)), InputError, "reference_images"),
])
def test_locate_bad_input(rt, scene, args, error, match):
    with pytest.raises(error) as info:
        rt.locate(*args(rt, scene))
    assert_typed(info, ValueError, match)


def test_render_wrong_scene_type(rt):
    with pytest.raises(InputError) as info:
        rt.render(12, 0, height=2, width=2)
    assert_typed(info, ValueError, "images")


# ----------------------------------------------------------------------------------------------
# iris-render (in process: main() returns the exit code, errors are one line on stderr)
# ----------------------------------------------------------------------------------------------

def _cli(capsys, *args) -> tuple[int, str]:
    code = render_main([str(a) for a in args])
    err = capsys.readouterr().err
    return code, err


@pytest.fixture
def photo(tmp_path) -> Path:
    path = tmp_path / "in.png"
    Image.fromarray(np.random.default_rng(1).integers(0, 256, (40, 50, 3), dtype=np.uint8)).save(path)
    return path


@pytest.mark.parametrize("case", ["empty_file", "truncated", "text", "huge_size", "nan_pose",
                                  "tampered", "external_data", "huge_chunk"])
def test_cli_errors_write_nothing(model_copy, photo, tmp_path, capsys, case):
    out = tmp_path / "out"
    args = [model_copy, photo, "-o", out, "--view", 0]
    bad = tmp_path / "bad.png"
    if case == "empty_file":
        bad.write_bytes(b"")
        args[1] = bad
    elif case == "truncated":
        bad.write_bytes(photo.read_bytes()[:80])
        args[1] = bad
    elif case == "text":
        bad.write_text("hello")
        args[1] = bad
    elif case == "huge_size":
        args += ["--size", "100000x100000"]
    elif case == "nan_pose":
        (tmp_path / "p.json").write_text(json.dumps(np.full((4, 4), np.nan).tolist()))
        args += ["--pose", tmp_path / "p.json"]
    elif case == "tampered":
        data = bytearray((model_copy / "encoder.onnx").read_bytes())
        data[-10] ^= 1
        (model_copy / "encoder.onnx").write_bytes(bytes(data))
    elif case == "external_data":
        import hashlib
        data = _graph_with_external_data("../../etc/passwd")
        (model_copy / "renderer.onnx").write_bytes(data)
        _edit_manifest(model_copy, lambda d: d["graphs"]["renderer"].update(
            sha256=hashlib.sha256(data).hexdigest()))
    elif case == "huge_chunk":
        args += ["--size", "1024x1024", "--chunk-rays", 1 << 20]
    code, err = _cli(capsys, *args)
    assert code == 2, err
    assert err.startswith("iris-render: error:") and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err
    assert not out.exists()


def test_cli_converts_grayscale_rgba_16bit(model_dir, tmp_path, capsys):
    import cv2
    rng = np.random.default_rng(2)
    paths = [tmp_path / "g.png", tmp_path / "a.png", tmp_path / "d.png"]
    Image.fromarray(rng.integers(0, 256, (30, 30), dtype=np.uint8)).save(paths[0])
    Image.fromarray(rng.integers(0, 256, (30, 30, 4), dtype=np.uint8)).save(paths[1])
    cv2.imwrite(str(paths[2]), rng.integers(0, 65536, (30, 30, 3), dtype=np.uint16))
    out = tmp_path / "out"
    code, err = _cli(capsys, model_dir, *paths, "-o", out, "--view", 1, "--size", "4x4",
                     "--no-depth", "--threads", 1, "-q")
    assert code == 0, err
    assert Image.open(out / "view_001.png").size == (4, 4)


# ----------------------------------------------------------------------------------------------
# iris-export (needs torch)
# ----------------------------------------------------------------------------------------------

@pytest.mark.torch
def test_export_errors_are_iris_errors(tmp_path, capsys):
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from export.cli import main as export_main
    from export.errors import (ExportArgumentError, ExportError, OutputExistsError,
                               ValidationError)
    from export.pipeline import export_model
    from iris_train.model import CheckpointError
    for cls in (ExportError, OutputExistsError, ExportArgumentError, ValidationError,
                CheckpointError):
        assert issubclass(cls, IrisError)
    assert issubclass(ExportArgumentError, ValueError) and issubclass(CheckpointError, ValueError)
    assert issubclass(OutputExistsError, OSError)

    out = tmp_path / "out"
    for bad, match in ((42, "model_or_ckpt"), (None, "model_or_ckpt"),
                       (tmp_path / "missing.pt", "no such file"), (tmp_path, "no such file")):
        with pytest.raises(IrisError, match=match):
            export_model(bad, out, progress=False)
    (tmp_path / "text.pt").write_text("not a checkpoint")
    for args, match in (([tmp_path / "text.pt", out], "text.pt"),
                        ([tmp_path / "text.pt", out, "--opset", "3"], "opset"),
                        ([tmp_path / "text.pt", out, "--threads", "0"], "threads")):
        code = export_main([str(a) for a in args] + ["-q"])
        err = capsys.readouterr().err
        assert code == 2 and match in err and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["text.pt"]       # nothing left behind


# ----------------------------------------------------------------------------------------------
# iris-train / iris-eval data loading
# ----------------------------------------------------------------------------------------------

def _scene_folder(root: Path, name: str, files: dict) -> Path:
    d = root / name
    d.mkdir(parents=True)
    for fname, content in files.items():
        (d / fname).write_bytes(content)
    return d


@pytest.mark.torch
@pytest.mark.parametrize("content, match", [
    (b"", "empty"), (b"GIF89a garbage", "not a readable image"), ("truncated", "not a readable"),
])
def test_data_folder_bad_images(tmp_path, content, match):
    pytest.importorskip("torch")
    from iris_train.data import load_dataset_folder, load_scene_folder
    good = _png_bytes(np.random.default_rng(0).integers(0, 256, (20, 20, 3), dtype=np.uint8))
    if content == "truncated":
        content = good[:len(good) // 2]                     # cut inside the image data
    folder = _scene_folder(tmp_path / "data", "s0", {"a.png": good, "b.png": content})
    for load in (load_scene_folder, lambda p: load_dataset_folder(p.parent)):
        with pytest.raises(ImageError) as info:
            load(folder)
        assert_typed(info, ValueError, "b.png", match)


@pytest.mark.torch
def test_data_folder_converts_grayscale_rgba_16bit(tmp_path):
    pytest.importorskip("torch")
    import cv2
    from iris_train.data import load_scene_folder
    rng = np.random.default_rng(4)
    gray = rng.integers(0, 256, (20, 20), dtype=np.uint8)
    deep = rng.integers(0, 65536, (20, 20, 3), dtype=np.uint16)
    folder = _scene_folder(tmp_path, "s", {"a.png": _png_bytes(gray),
                                           "b.png": _png_bytes(np.dstack([gray] * 4))})
    cv2.imwrite(str(folder / "c.png"), deep)
    scene = load_scene_folder(folder, size=(20, 20))
    assert scene.images.shape == (3, 20, 20, 3) and scene.images.dtype == np.uint8
    np.testing.assert_array_equal(scene.images[0], np.dstack([gray] * 3))
    np.testing.assert_array_equal(scene.images[1], np.dstack([gray] * 3))
    np.testing.assert_array_equal(scene.images[2], ((deep[..., ::-1].astype(np.uint32) * 2 + 257)
                                                    // 514).astype(np.uint8))


@pytest.mark.torch
def test_eval_data_and_model_errors(tmp_path, capsys):
    pytest.importorskip("torch")
    from iris_train.evaluate import load_evaluable, load_scenes
    from iris_train.evaluate import main as eval_main
    for data, match in (("synthetic:train", "synthetic"), (str(tmp_path / "none"), "not a folder")):
        with pytest.raises(InputError) as info:
            load_scenes(data, (64, 64))
        assert_typed(info, ValueError, "DATA", match)
    (tmp_path / "empty_model").mkdir()
    with pytest.raises(ModelFileError) as info:
        load_evaluable(tmp_path / "empty_model")
    assert_typed(info, OSError, "iris.json")
    with pytest.raises(IrisError, match="no such file"):
        load_evaluable(tmp_path / "missing.pt")
    code = eval_main([str(tmp_path / "missing.pt"), "synthetic:heldout", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("iris-eval: error:") and "Traceback" not in err


@pytest.mark.torch
def test_train_bad_preset_and_config(tmp_path, capsys):
    pytest.importorskip("torch")
    from iris_train.config import ModelConfig, preset
    from iris_train.train import main as train_main
    with pytest.raises(SystemExit) as info:
        train_main(["--out", str(tmp_path / "run"), "--preset", "huge"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "unknown preset 'huge'" in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()
    for bad in (lambda: preset("huge"), lambda: ModelConfig(image_height=60),
                lambda: ModelConfig(near=1.0, far=0.5), lambda: ModelConfig.from_dict({"x": 1})):
        with pytest.raises(InputError):
            bad()

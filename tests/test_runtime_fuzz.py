"""A bounded property-based fuzz of the runtime's public entries, ``IrisRuntime.encode``,
``render`` and ``locate``: random shapes and dtypes of images, NaN and inf, huge, negative and
non-integer sizes, poses rigid, nearly rigid, non-rigid, far, of the wrong shape or not numbers,
view indices out of range, random intrinsics, knobs and presets. Every call either returns what
its docstring says or raises the project's typed error (``iris_runtime.errors.IrisError``):
never a bare numpy / onnxruntime / OpenCV / Pillow exception, and never a numpy
``RuntimeWarning`` (overflow, invalid value: turned into errors here, as with
``-W error::RuntimeWarning``).
"""
from __future__ import annotations

import traceback
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from iris_runtime import IrisRuntime
from iris_runtime.errors import IrisError

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")

REPO = Path(__file__).resolve().parents[1]
PHOTOS = sorted((REPO / "samples" / "heldout-1000003").glob("frame_*.png"))
FUZZ = settings(deadline=None, database=None, derandomize=True,
                suppress_health_check=list(HealthCheck))


@pytest.fixture(scope="module")
def rt(model_dir):
    return IrisRuntime(model_dir, threads=1)


@pytest.fixture(scope="module")
def scene(rt):
    return rt.encode(PHOTOS[:2])


def typed_or_ok(call):
    """``call()``'s value, or None when it raised an ``IrisError``; any other exception (or a
    RuntimeWarning, an error here) fails with its traceback."""
    try:
        return call()
    except IrisError:
        return None
    except BaseException as exc:                                   # noqa: BLE001
        pytest.fail(f"{type(exc).__name__} (not an IrisError): {exc}\n"
                    f"{''.join(traceback.format_exception(exc))}")


numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-2**70, 2**70))
dtypes = st.sampled_from([np.uint8, np.uint16, np.int8, np.int32, np.int64, np.float16,
                          np.float32, np.float64, np.bool_, np.complex64])


@st.composite
def arrays(draw):
    """An image-like array of a random shape (0 to 5 dimensions, sides 0..24) and dtype, with
    random values (NaN, inf and out-of-range values for floats)."""
    shape = tuple(draw(st.lists(st.integers(0, 24), max_size=5)))
    if draw(st.booleans()):                       # image-like shapes more often
        shape = (draw(st.integers(0, 24)), draw(st.integers(0, 24)),
                 *draw(st.sampled_from([(), (1,), (3,), (4,), (2,), (5,)])))
    dtype = draw(dtypes)
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    size = int(np.prod(shape)) if shape else 1
    kind = draw(st.sampled_from(["unit", "wide", "special"]))
    values = {"unit": rng.random(size), "wide": rng.normal(0, 1e4, size),
              "special": rng.choice([np.nan, np.inf, -np.inf, 0.0, 1.0, -1.0, 1e300], size)}[kind]
    if not np.issubdtype(dtype, np.floating) and not np.issubdtype(dtype, np.complexfloating):
        values = np.nan_to_num(values, nan=0, posinf=0, neginf=0)
        info = np.iinfo(dtype) if dtype != np.bool_ else None
        values = values * 255 if info is None or info.max > 255 else values * info.max
        values = values if info is None else np.clip(values, info.min, info.max)
    with np.errstate(all="ignore"):
        return values.astype(dtype).reshape(shape)


images = st.one_of(arrays(), st.sampled_from(PHOTOS).map(str), st.sampled_from(PHOTOS),
                   st.binary(max_size=64), st.just("/no/such/photo.png"), numbers, st.none(),
                   st.text(max_size=5), st.lists(st.integers(0, 255), max_size=4))


@st.composite
def poses(draw):
    kind = draw(st.sampled_from(["rigid", "near", "scaled", "matrix", "shape", "index", "far",
                                 "other"]))
    a = draw(st.floats(-np.pi, np.pi))
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = draw(st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3))
    if kind == "near":
        T[:3, :3] += draw(st.floats(-2e-3, 2e-3))
    elif kind == "scaled":
        T[:3, :3] *= draw(st.floats(-3, 3))
    elif kind == "matrix":
        rows = draw(st.lists(st.lists(numbers, min_size=4, max_size=4), min_size=4,
                             max_size=4))
        return np.array(rows, dtype=np.float64) if draw(st.booleans()) else rows
    elif kind == "shape":
        return np.zeros(tuple(draw(st.lists(st.integers(0, 5), max_size=3))))
    elif kind == "index":
        return draw(st.integers(-3, 5) | st.booleans() | st.sampled_from([np.int64(1),
                                                                          np.float64(1.0)]))
    elif kind == "far":
        T[:3, 3] = draw(st.sampled_from([1e3, 1e6, 1e12, 1e200, 1e308]))
    elif kind == "other":
        return draw(st.none() | st.text(max_size=4) | st.just([[1, 2], [3]]))
    return T if draw(st.booleans()) else T.tolist()


sizes = st.one_of(st.none(), st.integers(1, 12), st.integers(1, 12), st.integers(-3, 0),
                  st.sampled_from([2**20, 2**40, 2**63, 10**30]), st.floats(-2, 20),
                  st.booleans(), st.text(max_size=2), st.sampled_from([np.int32(8),
                                                                       np.uint8(4)]))
qualities = st.one_of(st.none(), st.sampled_from(["auto", "exact", "balanced", "fast",
                                                  "adaptive", "ultra", ""]), numbers)


@settings(FUZZ, max_examples=120)
@given(pose=poses(), height=sizes, width=sizes, quality=qualities, depth=st.booleans(),
       extra=st.dictionaries(st.sampled_from(["samples", "top_k", "scale", "precision",
                                              "chunk_rays", "intrinsics", "refine", "colour"]),
                             numbers | st.none() | st.sampled_from(["int8", "ray", "x"])
                             | arrays(), max_size=2))
def test_render_fuzz(rt, scene, pose, height, width, quality, depth, extra):
    out = typed_or_ok(lambda: rt.render(scene, pose, height=height, width=width,
                                        quality=quality, depth=depth, **extra))
    if out is not None:
        image = out.image if depth else out
        assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
        if depth:
            assert np.all(np.isfinite(out.depth))


@settings(FUZZ, max_examples=60)
@given(items=st.one_of(st.lists(images, max_size=4), images),
       cameras=st.none() | st.sampled_from(["model", "epipolar", "refined", "magic"]) | numbers)
def test_encode_fuzz(rt, items, cameras):
    out = typed_or_ok(lambda: rt.encode(items, cameras=cameras))
    if out is not None:
        assert np.all(np.isfinite(out.world_from_cam)) and out.num_views >= 1


@settings(FUZZ, max_examples=60)
@given(image=st.one_of(images, st.lists(images, max_size=3)))
def test_locate_fuzz(rt, scene, image):
    out = typed_or_ok(lambda: rt.locate(scene, image))
    if out is not None:
        assert np.all(np.isfinite(out)) and out.shape[-2:] == (4, 4)

"""The declarative I/O spec of the two IRIS graphs: names, dtypes, axes, tolerances.

Export builds the graphs with these names and dynamic axes, validation checks the tolerances, and
the manifest (``iris.json``) carries this spec so that the runtime reads the same names without
importing this package (``iris_runtime`` never imports torch or ``export``).

Axis names: V views, R rays, S samples per ray; C' field channels, h x w feature grid, H x W the
model's image size. Everything per view is view-major ([V', R, S, ...]) because that is how the
runtime's numpy projection produces it.
"""
from __future__ import annotations

#: 2: the encoder takes ``is_reference`` (isolated references, queries located in their frame).
IO_SPEC_VERSION = 2

#: ONNX opset of the graphs unless ``--opset`` says otherwise: 20 has ``Gelu`` and the current
#: ``GridSample``; onnxruntime >= 1.17 runs it.
DEFAULT_OPSET = 20
#: The dynamo exporter silently raises lower opsets to 18, so export refuses them instead.
MIN_OPSET = 18

ENCODER = {
    "file": "encoder.onnx",
    "inputs": {
        # RGB in [0, 1] at the model's resolution (H, W fixed, recorded in the manifest).
        "images": {"dtype": "float32", "shape": ["V", 3, "H", "W"]},
        # True: a reference (its tokens attend to references only, so its outputs never depend on
        # the queries); False: a query (attends to the references and to itself; its pose comes
        # out in the references' frame). View 0 must be a reference. All True = encode a scene.
        "is_reference": {"dtype": "bool", "shape": ["V"]},
    },
    "outputs": {
        # Per-scene field maps (LatentField.prepare of the encoder features): what the renderer samples.
        "field_maps": {"dtype": "float32", "shape": ["V", "C'", "h", "w"]},
        "world_from_cam": {"dtype": "float32", "shape": ["V", 4, 4]},    # view 0 = I
        "focal": {"dtype": "float32", "shape": [2]},                    # (fx/W, fy/H)
    },
    "dynamic_axes": {"images": {0: "V"}, "is_reference": {0: "V"}, "field_maps": {0: "V"},
                     "world_from_cam": {0: "V"}},
    # Max abs error of ONNX Runtime vs torch on the probe inputs.
    "tolerance": {"field_maps": 1e-4, "world_from_cam": 1e-5, "focal": 1e-5},
    # Max abs change of the references' outputs in ONNX Runtime when queries are added, changed or
    # removed (export.validate.isolation_errors).
    "isolation_tolerance": 1e-6,
}

RENDERER = {
    "file": "renderer.onnx",
    "inputs": {
        "field_maps": {"dtype": "float32", "shape": ["V", "C'", "h", "w"]},
        # Normalised sample positions in each view, grid_sample convention (align_corners=False).
        "grid": {"dtype": "float32", "shape": ["V", "R", "S", 2]},
        "cues": {"dtype": "float32", "shape": ["V", "R", "S", 4]},         # geometric cue Δ
        "mask": {"dtype": "bool", "shape": ["V", "R", "S"]},               # valid projection
        "positions": {"dtype": "float32", "shape": ["R", "S", 3]},
        "directions": {"dtype": "float32", "shape": ["R", 3]},
    },
    "outputs": {
        "rgb": {"dtype": "float32", "shape": ["R", 3]},
        "weights": {"dtype": "float32", "shape": ["R", "S"]},
    },
    "dynamic_axes": {
        "field_maps": {0: "V"}, "grid": {0: "V", 1: "R", 2: "S"}, "cues": {0: "V", 1: "R", 2: "S"},
        "mask": {0: "V", 1: "R", 2: "S"}, "positions": {0: "R", 1: "S"}, "directions": {0: "R"},
        "rgb": {0: "R"}, "weights": {0: "R", 1: "S"},
    },
    "tolerance": {"rgb": 1e-4, "weights": 1e-4},
}

GRAPHS = {"encoder": ENCODER, "renderer": RENDERER}

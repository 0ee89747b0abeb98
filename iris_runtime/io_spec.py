"""The contract between ``iris-export`` and the runtime, declared once: the manifest's name, format
and version, and the declarative I/O spec of the two graphs (names, dtypes, axes, tolerances).

Export (``export/``) builds the graphs with these names and dynamic axes, validation checks the
tolerances, and the manifest (``iris.json``) carries the spec; the runtime's manifest reader
(``iris_runtime.manifest``) checks a model against it. Torch-free, so both sides import it.

Axis names: V views, R rays, S samples per ray; C' field channels, h x w feature grid, H x W the
model's image size. Everything per view is view-major ([V', R, S, ...]) because that is how the
runtime's numpy projection produces it.
"""
from __future__ import annotations

#: The manifest that iris-export writes next to the graphs.
MANIFEST_NAME = "iris.json"
FORMAT_NAME = "iris-model"
#: Manifest format versions that shipped: 1 (the encoder took ``images`` only and every view saw
#: every other), 2 (the encoder takes ``is_reference``: isolated references, queries located in
#: their frame; ``IrisRuntime.locate``). The runtime reads 2 and refuses 1 with a re-export hint.
FORMAT_VERSION = 2

#: Version of the graphs' I/O names and layouts. Shipped: 1 (format 1's encoder), 2 (format 2:
#: ``is_reference``), 3 (the renderer of an explicit-colour model, ``config.explicit_rgb``, also
#: takes ``colours``; for every other model the two graphs are those of 2), 4 (the renderers'
#: ``mask`` is float32 validity weights, ``geometry.validity``, not bool).
IO_SPEC_VERSION = 4
#: I/O spec versions whose renderers take a bool ``mask``: the manifest reader refuses them with
#: a re-export hint (it reads ``IO_SPEC_VERSION`` only).
IO_SPEC_BOOL_MASK = (2, 3)

# The graphs' input and output names: the keys of the specs below, and what the runtime feeds and
# reads (``IrisRuntime``, ``raymarch``).
IMAGES, IS_REFERENCE = "images", "is_reference"
FIELD_MAPS, WORLD_FROM_CAM, FOCAL = "field_maps", "world_from_cam", "focal"
GRID, CUES, MASK, POSITIONS, DIRECTIONS = "grid", "cues", "mask", "positions", "directions"
COLOURS, GROUPS, PAIRS = "colours", "groups", "pairs"
RGB, WEIGHTS = "rgb", "weights"

ENCODER = {
    "file": "encoder.onnx",
    "inputs": {
        # RGB in [0, 1] at the model's resolution (H, W fixed, recorded in the manifest).
        IMAGES: {"dtype": "float32", "shape": ["V", 3, "H", "W"]},
        # True: a reference (its tokens attend to references only, so its outputs never depend on
        # the queries); False: a query (attends to the references and to itself; its pose comes
        # out in the references' frame). View 0 must be a reference. All True = encode a scene.
        IS_REFERENCE: {"dtype": "bool", "shape": ["V"]},
    },
    "outputs": {
        # Per-scene field maps (LatentField.prepare of the encoder features): what the renderer samples.
        FIELD_MAPS: {"dtype": "float32", "shape": ["V", "C'", "h", "w"]},
        WORLD_FROM_CAM: {"dtype": "float32", "shape": ["V", 4, 4]},      # view 0 = I
        FOCAL: {"dtype": "float32", "shape": [2]},                       # (fx/W, fy/H)
    },
    "dynamic_axes": {IMAGES: {0: "V"}, IS_REFERENCE: {0: "V"}, FIELD_MAPS: {0: "V"},
                     WORLD_FROM_CAM: {0: "V"}},
    # Max abs error of ONNX Runtime vs torch on the probe inputs.
    "tolerance": {FIELD_MAPS: 1e-4, WORLD_FROM_CAM: 1e-5, FOCAL: 1e-5},
    # Max abs change of the references' outputs in ONNX Runtime when queries are added, changed or
    # removed (export.validate.isolation_errors).
    "isolation_tolerance": 1e-6,
}

RENDERER = {
    "file": "renderer.onnx",
    "inputs": {
        FIELD_MAPS: {"dtype": "float32", "shape": ["V", "C'", "h", "w"]},
        # Normalised sample positions in each view, grid_sample convention (align_corners=False).
        GRID: {"dtype": "float32", "shape": ["V", "R", "S", 2]},
        CUES: {"dtype": "float32", "shape": ["V", "R", "S", 4]},         # geometric cue Δ
        # Validity weight of each sample in each view, in [0, 1] (geometry.validity: 1 in the
        # image, fading to 0 within EDGE_FADE pixels outside it; 0 masks the pair out).
        MASK: {"dtype": "float32", "shape": ["V", "R", "S"]},
        POSITIONS: {"dtype": "float32", "shape": ["R", "S", 3]},
        DIRECTIONS: {"dtype": "float32", "shape": ["R", 3]},
    },
    "outputs": {
        RGB: {"dtype": "float32", "shape": ["R", 3]},
        WEIGHTS: {"dtype": "float32", "shape": ["R", "S"]},
    },
    "dynamic_axes": {
        FIELD_MAPS: {0: "V"}, GRID: {0: "V", 1: "R", 2: "S"}, CUES: {0: "V", 1: "R", 2: "S"},
        MASK: {0: "V", 1: "R", 2: "S"}, POSITIONS: {0: "R", 1: "S"}, DIRECTIONS: {0: "R"},
        RGB: {0: "R"}, WEIGHTS: {0: "R", 1: "S"},
    },
    "tolerance": {RGB: 1e-4, WEIGHTS: 1e-4},
}

#: The renderer's extra input for explicit-colour models (``ModelConfig.explicit_rgb``), listed in
#: their spec only (``spec_for``): the reference photos' RGB in [0, 1] at each sample's projection
#: into each view, bilinear on the full-resolution image with the same normalised ``grid`` as the
#: field maps (align_corners=False, border-clamped), sampled by the caller in numpy
#: (``iris_runtime.geometry.sample_taps``). Masked (view, sample) entries are ignored by the graph
#: (any finite value). The graph adds ``rgb_to_maps(colours - 0.5)`` to the sampled field maps,
#: takes each sample's validity-weighted mean colour over its views and blends it along the ray;
#: ``weights`` are then the blend weights.
#:
#: Sampled in numpy, not in the graph: about as fast as ``GridSample`` on the photos, far cheaper
#: than a dense weight matrix over the full-resolution image, keeps every graph input per sample
#: and reuses the runtime's tested sampler (docs/PERFORMANCE.md, "Renderer and encoder graphs").
EXPLICIT_RGB_INPUTS = {
    COLOURS: {"dtype": "float32", "shape": ["V", "R", "S", 3]},
}
EXPLICIT_RGB_AXES = {COLOURS: {0: "V", 1: "R", 2: "S"}}

#: The renderer on per-point pre-selected views (optional: iris-export writes it with the "fast"
#: renderer graphs; the runtime renders per-point top-k with it). The caller passes the (view,
#: point) pairs it keeps in P groups of G pairs, each group of one view (``groups``: its index into
#: ``field_maps``; ``grid``, ``cues``, ``colours`` at ``[p, g]``; unused padding entries: any
#: finite value), and per point K view slots: slot k of point (r, s) is pair ``pairs[k, r, s]``
#: (flat index p * G + g) with validity weight ``mask[k, r, s]`` (0: no pair). The result equals
#: ``RENDERER`` fed every view with the pairs not kept masked, so the sampling shrinks to the kept
#: pairs and the field's view axis to K. A point's slots must hold distinct views (a view held
#: twice would count twice). Built by ``point_views.select_point_views``.
RENDERER_VIEWS = {
    "file": "renderer_views.onnx",
    "inputs": {
        FIELD_MAPS: {"dtype": "float32", "shape": ["V", "C'", "h", "w"]},
        GROUPS: {"dtype": "int64", "shape": ["P"]},                      # in [0, V)
        GRID: {"dtype": "float32", "shape": ["P", "G", 2]},
        CUES: {"dtype": "float32", "shape": ["P", "G", 4]},
        PAIRS: {"dtype": "int64", "shape": ["K", "R", "S"]},             # in [0, P * G)
        MASK: {"dtype": "float32", "shape": ["K", "R", "S"]},            # slot's weight, 0: empty
        POSITIONS: {"dtype": "float32", "shape": ["R", "S", 3]},
        DIRECTIONS: {"dtype": "float32", "shape": ["R", 3]},
    },
    "outputs": RENDERER["outputs"],
    "dynamic_axes": {
        FIELD_MAPS: {0: "V"}, GROUPS: {0: "P"}, GRID: {0: "P", 1: "G"},
        CUES: {0: "P", 1: "G"}, PAIRS: {0: "K", 1: "R", 2: "S"},
        MASK: {0: "K", 1: "R", 2: "S"}, POSITIONS: {0: "R", 1: "S"}, DIRECTIONS: {0: "R"},
        RGB: {0: "R"}, WEIGHTS: {0: "R", 1: "S"},
    },
    "tolerance": RENDERER["tolerance"],
}

#: The camera half of the encoder (optional: iris-export writes it for a model whose camera head
#: reads an encoder of its own, ``config.camera_encoder``): ``ENCODER``'s inputs and its cameras,
#: without the field maps, whose encoder it does not run. The runtime runs it where it needs
#: cameras only: the refinement's start in the photos' canonical order, and ``locate``.
ENCODER_CAMERAS = {
    **ENCODER,
    "file": "encoder_cameras.onnx",
    **{key: {k: v for k, v in ENCODER[key].items() if k != FIELD_MAPS}
       for key in ("outputs", "dynamic_axes", "tolerance")},
}


GRAPHS = {"encoder": ENCODER, "renderer": RENDERER}
#: Graphs a model may have besides ``GRAPHS`` (read and checked when the manifest lists them).
OPTIONAL_GRAPHS = {"renderer_views": RENDERER_VIEWS, "encoder_cameras": ENCODER_CAMERAS}


def spec_for(graph: str, explicit_rgb: bool = False) -> dict:
    """The I/O spec of ``graph`` for a model with or without explicit colour.

    Without it: ``GRAPHS[graph]`` itself. With it, the renderer's spec gains ``colours`` as its
    last input; the other entries (``tolerance`` included) are the same objects as ``RENDERER``'s,
    so a change to ``RENDERER["tolerance"]`` applies to both."""
    spec = {**GRAPHS, **OPTIONAL_GRAPHS}[graph]
    if graph in ("encoder", "encoder_cameras") or not explicit_rgb:
        return spec
    if graph == "renderer_views":            # colours per kept pair, like grid and cues
        shape, axes = ["P", "G", 3], {0: "P", 1: "G"}
    else:
        shape, axes = EXPLICIT_RGB_INPUTS[COLOURS]["shape"], EXPLICIT_RGB_AXES[COLOURS]
    return {**spec, "inputs": {**spec["inputs"], COLOURS: {"dtype": "float32", "shape": shape}},
            "dynamic_axes": {**spec["dynamic_axes"], COLOURS: axes}}


def required_dtypes(graph: str, explicit_rgb: bool = False) -> dict[str, dict[str, str]]:
    """``{"inputs": {name: dtype}, "outputs": {name: dtype}}`` of ``spec_for(graph, explicit_rgb)``:
    what the runtime feeds and reads, so what a model's manifest must list."""
    spec = spec_for(graph, explicit_rgb)
    return {kind: {name: entry["dtype"] for name, entry in spec[kind].items()}
            for kind in ("inputs", "outputs")}


__all__ = ["MANIFEST_NAME", "FORMAT_NAME", "FORMAT_VERSION", "IO_SPEC_VERSION", "IO_SPEC_BOOL_MASK",
           "ENCODER", "RENDERER", "RENDERER_VIEWS", "ENCODER_CAMERAS", "EXPLICIT_RGB_INPUTS",
           "EXPLICIT_RGB_AXES", "GRAPHS", "OPTIONAL_GRAPHS", "spec_for", "required_dtypes",
           "IMAGES", "IS_REFERENCE", "FIELD_MAPS", "WORLD_FROM_CAM", "FOCAL", "GRID", "CUES", "MASK",
           "POSITIONS", "DIRECTIONS", "COLOURS", "GROUPS", "PAIRS", "RGB", "WEIGHTS"]

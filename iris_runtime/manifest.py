"""Read and check ``iris.json``, the manifest that ``iris-export`` writes next to the two graphs.

The manifest is the only thing the runtime knows about a model: the format tag and version, the
model's config, its image size, the ray sampling (near, far, samples), and per graph the file
name, its sha256 and its I/O spec (``iris_runtime.io_spec``, the one declaration that export
builds the graphs from, copied into the manifest; the runtime never imports ``export`` or torch).

Checks, each failing with a typed ``ModelFileError`` that names the file and what was expected:

- ``ManifestError``: ``iris.json`` missing, not JSON, a field missing or of the wrong type
  (``io_spec_version``, ``config``, ``image_size``, ``near``, ``far``, ``samples``,
  ``field_channels`` and ``graphs`` are all required: every format-2 exporter wrote them), a
  graph path that is absolute, contains ``..`` or resolves (through symlinks) outside the model
  directory, or an I/O spec that lacks a name the runtime feeds or reads;
- ``ModelFormatError``: format name other than ``"iris-model"`` or a version other than 2
  (version 1, written before the encoder isolated its references, says to re-export with
  iris-export); an ``io_spec_version`` other than ``IO_SPEC_VERSION`` (4; versions 2 and 3,
  whose renderers take a bool mask, say to re-export with iris-export);
- explicit colour: ``config.explicit_rgb`` (a bool; absent = False) says whether the renderer
  takes ``colours`` (``EXPLICIT_RGB_INPUTS``); a renderer spec that lists ``colours`` for a model
  without it, or lacks it for a model with it, is a ``ManifestError``;
- ``ModelIntegrityError``: a graph file whose sha256 differs from the manifest's (tampered,
  truncated or replaced); a missing graph file is a plain ``ModelFileError``;
- external data: iris-export writes self-contained graphs. A graph whose tensors refer to ONNX
  external data is refused before onnxruntime sees it (``check_self_contained``): a location that
  is absolute, contains ``..`` or resolves outside the model directory is a ``ManifestError``, any
  other one a ``ModelFileError``. (The runtime builds sessions from the checked bytes, and for a
  model loaded from bytes onnxruntime resolves external data against the process's working
  directory, not the model's, and older releases do not confine it at all.)
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath, PureWindowsPath
from types import MappingProxyType
from typing import Any, Mapping

from .errors import ManifestError, ModelFileError, ModelFormatError, ModelIntegrityError
from .fileio import read_json, sha256_bytes
from .io_spec import (EXPLICIT_RGB_INPUTS, FORMAT_NAME, FORMAT_VERSION, GRAPHS, IO_SPEC_BOOL_MASK,
                      IO_SPEC_VERSION, MANIFEST_NAME, OPTIONAL_GRAPHS, required_dtypes)


def required_io_for(explicit_rgb: bool) -> dict[str, dict[str, dict[str, str]]]:
    """Per graph, the input and output names the runtime feeds and reads, with their dtypes
    (``io_spec.required_dtypes``): a model whose manifest lacks one of these cannot be run. An
    explicit-colour model's renderer also takes ``colours``."""
    return {graph: required_dtypes(graph, explicit_rgb) for graph in GRAPHS}


@dataclass(frozen=True)
class GraphEntry:
    """One graph of the model: where it is, its recorded sha256, and its I/O spec."""
    name: str
    path: Path                                  # absolute, inside the model directory
    sha256: str
    inputs: Mapping[str, Mapping[str, Any]]     # name -> {"dtype": ..., "shape": [...]}
    outputs: Mapping[str, Mapping[str, Any]]


@dataclass(frozen=True)
class Manifest:
    """The checked contents of ``iris.json``."""
    model_dir: Path
    version: int
    config: Mapping[str, Any]
    image_size: tuple[int, int]                 # (H, W): the model's resolution
    near: float
    far: float
    samples: int
    field_channels: int                         # C' of the field maps
    graphs: Mapping[str, GraphEntry]
    raw: Mapping[str, Any] = field(repr=False)  # the whole document, for reports
    #: config.explicit_rgb: the renderer takes ``colours`` (the reference RGB at the samples).
    explicit_rgb: bool = False
    #: The cameras the renderer was trained with, and so ``IrisRuntime.encode``'s default:
    #: "model" (the camera head's), "solve" (``iris-train --render-cameras solve``) or "refined".
    #: Optional in the file; "model" when absent (every model exported before it existed).
    cameras: str = "model"
    #: Where the cameras' unit puts a scene's median point depth (``cameras.unit_range``); 0:
    #: ``DEPTH_TARGET`` of the way into [near, far]. Optional in the file (0 when absent).
    median_depth: float = 0.0

    @property
    def unit_range(self) -> tuple[float, float]:
        """The ``depth_range`` the camera solve is given: the cameras' unit
        (``cameras.unit_range``), [near, far] itself unless ``median_depth`` frees it."""
        from .cameras.solve import unit_range
        return unit_range(self.near, self.far, self.median_depth)

    @property
    def blend_angle(self) -> float:
        """config.blend_angle: the angular weighting of the views in the colour blend
        (``colour.mean_colour``; absent = 0, the plain mean)."""
        return float(self.config.get("blend_angle", 0.0))


#: The cameras a renderer can be given: the encoder's ("model"), the camera solve of the photos
#: ("solve": SIFT matches, incremental mapping and bundle adjustment,
#: ``iris_runtime.cameras.replace_model_cameras``) or the encoder's refined by the photos
#: ("refined", ``iris_runtime.cameras.refine_model_cameras``). The values of the manifest's
#: optional "cameras" (``Manifest.cameras``), of ``IrisRuntime.encode(cameras=...)``, of the
#: command lines' ``--cameras`` and of ``iris-train --render-cameras``.
CAMERAS = ("model", "solve", "refined")
#: Former names of those cameras, the one place they are kept: wherever a name is read (a
#: manifest, ``encode``, a command line, a request, a checkpoint's training config) it goes
#: through ``camera_name``, so that old manifests, requests and checkpoints keep working.
#: "epipolar": the solve's former name (docs/record/cameras-refactor.md).
CAMERA_ALIASES = {"epipolar": "solve"}


def camera_name(value):
    """``value`` read as a name of ``CAMERAS``: a former name (``CAMERA_ALIASES``) as its current
    one, anything else as given (the caller checks it against ``CAMERAS``)."""
    return CAMERA_ALIASES.get(value, value) if isinstance(value, str) else value


def read_graph_bytes(entry: GraphEntry) -> bytes:
    """The graph file's bytes, checked against the manifest's sha256 (what a session is built from,
    so the graph that runs is the graph that was checked, even if the file changes later)."""
    try:
        data = entry.path.read_bytes()
    except FileNotFoundError:
        raise ModelFileError(f"{entry.path}: {entry.name} graph file is missing") from None
    except OSError as exc:
        raise ModelFileError(f"{entry.path}: cannot read the {entry.name} graph: {exc}") from None
    _check_digest(entry, sha256_bytes(data))
    check_self_contained(entry, data)
    return data


# -- external data ------------------------------------------------------------------------------
# A minimal reader of the protobuf wire format, enough to find every TensorProto of an ONNX model
# (torch-free and onnx-free: the runtime depends on neither). Field numbers are onnx.proto3's.
_MODEL_GRAPH, _MODEL_FUNCTIONS = 7, 25
_GRAPH_NODE, _GRAPH_INITIALIZER, _GRAPH_SPARSE_INITIALIZER = 1, 5, 15
_FUNCTION_NODE = 7
_NODE_ATTRIBUTE = 5
_ATTR_T, _ATTR_G, _ATTR_TENSORS, _ATTR_GRAPHS, _ATTR_SPARSE, _ATTR_SPARSES = 5, 6, 10, 11, 22, 23
_SPARSE_VALUES, _SPARSE_INDICES = 1, 2
_TENSOR_EXTERNAL_DATA = 13
_ENTRY_KEY, _ENTRY_VALUE = 1, 2


def _varint(buf: memoryview, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        b = buf[i]
        i += 1
        value |= (b & 0x7F) << shift
        if b < 0x80:
            return value, i
        shift += 7
        if shift > 63:
            raise ValueError("varint too long")


def _fields(buf: memoryview):
    """(field number, payload) of each length-delimited field of one message; others skipped."""
    i, n = 0, len(buf)
    while i < n:
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            _, i = _varint(buf, i)
        elif wire == 1:
            i += 8
        elif wire == 5:
            i += 4
        elif wire == 2:
            length, i = _varint(buf, i)
            if i + length > n:
                raise ValueError("truncated field")
            yield number, buf[i:i + length]
            i += length
        else:
            raise ValueError(f"unsupported wire type {wire}")


def _tensor_locations(tensor: memoryview, out: list) -> None:
    external, location = False, ""
    for number, payload in _fields(tensor):
        if number == _TENSOR_EXTERNAL_DATA:
            external = True
            entry = dict(_fields(payload))
            if bytes(entry.get(_ENTRY_KEY, b"")) == b"location":
                location = bytes(entry.get(_ENTRY_VALUE, b"")).decode("utf-8", "replace")
    if external:
        out.append(location)


def _graph_locations(graph: memoryview, out: list, depth: int = 0) -> None:
    if depth > 64:
        raise ValueError("graphs nested too deeply")
    for number, payload in _fields(graph):
        if number == _GRAPH_INITIALIZER:
            _tensor_locations(payload, out)
        elif number == _GRAPH_SPARSE_INITIALIZER:
            _sparse_locations(payload, out)
        elif number == _GRAPH_NODE:
            _node_locations(payload, out, depth)


def _sparse_locations(sparse: memoryview, out: list) -> None:
    for number, payload in _fields(sparse):
        if number in (_SPARSE_VALUES, _SPARSE_INDICES):
            _tensor_locations(payload, out)


def _node_locations(node: memoryview, out: list, depth: int) -> None:
    for number, payload in _fields(node):
        if number != _NODE_ATTRIBUTE:
            continue
        for a_number, a_payload in _fields(payload):
            if a_number in (_ATTR_T, _ATTR_TENSORS):
                _tensor_locations(a_payload, out)
            elif a_number in (_ATTR_G, _ATTR_GRAPHS):
                _graph_locations(a_payload, out, depth + 1)
            elif a_number in (_ATTR_SPARSE, _ATTR_SPARSES):
                _sparse_locations(a_payload, out)


def external_data_locations(data: bytes) -> list[str] | None:
    """Locations of the external data that the tensors of the ONNX model ``data`` refer to (``[]``
    for a self-contained model), or None when ``data`` is not a parseable protobuf message."""
    out: list[str] = []
    try:
        for number, payload in _fields(memoryview(data)):
            if number == _MODEL_GRAPH:
                _graph_locations(payload, out)
            elif number == _MODEL_FUNCTIONS:
                for f_number, f_payload in _fields(payload):
                    if f_number == _FUNCTION_NODE:
                        _node_locations(f_payload, out, 0)
    except (IndexError, ValueError):
        return None                 # not protobuf: onnxruntime refuses it with its own error
    return out


def check_self_contained(entry: GraphEntry, data: bytes) -> None:
    """Refuse a graph whose tensors refer to external data (see the module docstring)."""
    locations = external_data_locations(data)
    if not locations:
        return
    root = entry.path.parent
    for location in locations:
        posix, windows = PurePosixPath(location), PureWindowsPath(location)
        escapes = (posix.is_absolute() or windows.is_absolute() or bool(windows.drive)
                   or ".." in posix.parts or ".." in windows.parts
                   or not (root / location).resolve().is_relative_to(root))
        if escapes:
            raise ManifestError(f"{entry.path}: the {entry.name} graph refers to external data "
                                f"{location!r}, which points outside the model directory {root}")
    raise ModelFileError(f"{entry.path}: the {entry.name} graph refers to external data "
                         f"{locations[0]!r}; expected a self-contained graph (as iris-export "
                         f"writes it)")


def read_manifest(model_dir: str | os.PathLike, *, verify_hashes: bool = True) -> Manifest:
    """Read ``model_dir/iris.json`` and check it (see the module docstring); with
    ``verify_hashes`` also hash each graph file against the manifest."""
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise ModelFileError(f"model directory {str(model_dir)!r}: no such directory "
                             f"(expected the output directory of iris-export)")
    path = model_dir / MANIFEST_NAME
    doc = read_json(path, what=f"the {MANIFEST_NAME} manifest written by iris-export",
                    error=ManifestError)
    version = _check_format(path, doc)
    config, explicit_rgb = _check_config(path, doc)
    size = doc.get("image_size")
    if (not isinstance(size, (list, tuple)) or len(size) != 2
            or not all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size)):
        raise ManifestError(f"{path}: 'image_size' must be [height, width] positive integers, "
                            f"got {size!r}")
    near, far = _number(path, doc, "near"), _number(path, doc, "far")
    if not 0 < near < far:
        raise ManifestError(f"{path}: need 0 < near < far, got near={near}, far={far}")
    # Optional (0 when absent: every model exported before it existed).
    median_depth = _number(path, doc, "median_depth") if "median_depth" in doc else 0.0
    if median_depth and not near < median_depth < far:
        raise ManifestError(f"{path}: 'median_depth' must be 0 or in (near, far) = ({near}, "
                            f"{far}), got {median_depth}")
    samples = _number(path, doc, "samples", kind=int)
    field_channels = _number(path, doc, "field_channels", kind=int)
    root = model_dir.resolve()
    graphs = _graph_entries(path, root, doc.get("graphs"), explicit_rgb)
    cameras = camera_name(doc.get("cameras", "model"))
    if cameras not in CAMERAS:
        raise ManifestError(f"{path}: 'cameras' must be one of {list(CAMERAS)}, got "
                            f"{cameras!r}")
    manifest = Manifest(model_dir=root, version=version, config=MappingProxyType(dict(config)),
                        image_size=(int(size[0]), int(size[1])), near=near, far=far,
                        samples=samples, field_channels=field_channels,
                        graphs=MappingProxyType(graphs),
                        raw=MappingProxyType(doc), explicit_rgb=explicit_rgb, cameras=cameras,
                        median_depth=median_depth)
    if verify_hashes:
        for entry in graphs.values():
            if not entry.path.is_file():
                raise ModelFileError(f"{entry.path}: {entry.name} graph file is missing "
                                     f"(listed in {path})")
            data = entry.path.read_bytes()
            _check_digest(entry, sha256_bytes(data))
            check_self_contained(entry, data)
    return manifest


def _check_format(path: Path, doc: dict) -> int:
    """The manifest's format, version and I/O spec version checked -> its version."""
    fmt, version = doc.get("format"), doc.get("version")
    if fmt != FORMAT_NAME:
        raise ModelFormatError(f"{path}: format {fmt!r}, expected {FORMAT_NAME!r} "
                               f"(the manifest of an iris-export model directory)")
    if version == 1 and not isinstance(version, bool):       # the one earlier format that shipped
        raise ModelFormatError(f"{path}: {FORMAT_NAME} version 1, written before the encoder "
                               f"isolated its references (its graph has no 'is_reference' input); "
                               f"this runtime reads version {FORMAT_VERSION}: re-export with "
                               f"iris-export (the checkpoint still loads: iris-export CKPT OUT)")
    if version != FORMAT_VERSION or isinstance(version, bool):
        raise ModelFormatError(f"{path}: {FORMAT_NAME} version {version!r}; this runtime reads "
                               f"version {FORMAT_VERSION} (re-export with iris-export, or upgrade "
                               f"iris_runtime)")

    io_version = doc.get("io_spec_version")
    if io_version in IO_SPEC_BOOL_MASK:
        raise ModelFormatError(f"{path}: I/O spec version {io_version}, written before validity "
                               f"weights (its renderer takes a bool mask); this runtime feeds "
                               f"I/O spec version {IO_SPEC_VERSION}: re-export with iris-export "
                               f"(the checkpoint still loads: iris-export CKPT OUT)")
    if isinstance(io_version, bool) or io_version != IO_SPEC_VERSION:
        raise ModelFormatError(f"{path}: I/O spec version {io_version!r}; this runtime feeds I/O "
                               f"spec version {IO_SPEC_VERSION} (re-export with iris-export, or "
                               f"upgrade iris_runtime)")
    return version


def _check_config(path: Path, doc: dict) -> tuple[dict, bool]:
    """The manifest's "config" checked -> ``(config, explicit_rgb)``."""
    config = doc.get("config")
    if not isinstance(config, dict):
        raise ManifestError(f"{path}: 'config' must be an object, got {type(config).__name__}")
    explicit_rgb = config.get("explicit_rgb", False)
    if not isinstance(explicit_rgb, bool):
        raise ManifestError(f"{path}: config.explicit_rgb must be true or false, got "
                            f"{explicit_rgb!r}")
    angle = config.get("blend_angle", 0.0)
    if (isinstance(angle, bool) or not isinstance(angle, (int, float))
            or not 0 <= angle < math.inf or (angle and not explicit_rgb)):
        raise ManifestError(f"{path}: config.blend_angle must be a finite number >= 0, and 0 "
                            f"without explicit_rgb, got {angle!r}")
    return config, explicit_rgb


def _number(path: Path, doc: dict, key: str, kind=float):
    """``doc[key]`` as a finite float, or (``kind=int``) a positive integer."""
    value = doc.get(key)
    ok = (isinstance(value, (int, float)) and not isinstance(value, bool)
          and math.isfinite(value))
    if kind is int:
        ok = ok and float(value).is_integer() and value > 0
    if not ok:
        what = "a positive integer" if kind is int else "a finite number"
        raise ManifestError(f"{path}: {key!r} must be {what}, got {value!r}")
    return kind(value)


def _graph_entries(path: Path, root: Path, graphs_doc, explicit_rgb: bool) -> dict[str, GraphEntry]:
    """The manifest's "graphs" checked -> ``GraphEntry`` by name: the required graphs, the
    optional ones listed, and the variants of a required one."""
    if not isinstance(graphs_doc, dict):
        raise ManifestError(f"{path}: 'graphs' must be an object with 'encoder' and 'renderer'")
    graphs = {}
    required_io = required_io_for(explicit_rgb)
    for name, required in required_io.items():
        entry = graphs_doc.get(name)
        if not isinstance(entry, dict):
            raise ManifestError(f"{path}: graphs.{name} missing (expected an object with 'file', "
                                f"'sha256', 'inputs', 'outputs')")
        graphs[name] = _graph_entry(path, root, name, entry, required)
    # Optional graphs (io_spec.OPTIONAL_GRAPHS, e.g. "renderer_views"): checked when listed.
    for name in OPTIONAL_GRAPHS:
        entry = graphs_doc.get(name)
        if entry is not None:
            if not isinstance(entry, dict):
                raise ManifestError(f"{path}: graphs.{name} must be an object with 'file', "
                                    f"'sha256', 'inputs', 'outputs'")
            graphs[name] = _graph_entry(path, root, name, entry,
                                        required_dtypes(name, explicit_rgb))
    # Variants of a graph (e.g. "renderer_int8", written by iris-export --quantize int8) have the
    # I/O of the graph they stand in for.
    for name, entry in graphs_doc.items():
        base = entry.get("variant_of") if isinstance(entry, dict) else None
        if name not in graphs and base in required_io:
            graphs[name] = _graph_entry(path, root, name, entry, required_io[base])
    for name, entry in graphs.items():
        if name != "encoder" and not explicit_rgb and set(EXPLICIT_RGB_INPUTS) & set(entry.inputs):
            raise ManifestError(f"{path}: graphs.{name}.inputs lists {sorted(EXPLICIT_RGB_INPUTS)}, "
                                f"but config.explicit_rgb is not true (a renderer without explicit "
                                f"colour takes no reference RGB)")
    return graphs


def _graph_entry(path: Path, root: Path, name: str, entry: dict, required: dict) -> GraphEntry:
    where = f"{path}: graphs.{name}"
    file = entry.get("file")
    if not isinstance(file, str) or not file:
        raise ManifestError(f"{where}.file must be a file name, got {file!r}")
    # Reject anything that could leave the model directory, in either path syntax, before
    # touching the file system; then check the resolved path too (symlinks).
    posix, windows = PurePosixPath(file), PureWindowsPath(file)
    if posix.is_absolute() or windows.is_absolute() or windows.drive or ".." in posix.parts \
            or ".." in windows.parts:
        raise ManifestError(f"{where}.file {file!r}: expected a path relative to the model "
                            f"directory, without '..'")
    resolved = (root / file).resolve()
    if not resolved.is_relative_to(root):
        raise ManifestError(f"{where}.file {file!r} resolves to {resolved}, outside the model "
                            f"directory {root}")
    digest = entry.get("sha256")
    if not isinstance(digest, str) or len(digest) != 64 or any(c not in "0123456789abcdef"
                                                               for c in digest.lower()):
        raise ManifestError(f"{where}.sha256 must be 64 hex digits, got {digest!r}")
    io = {}
    for kind in ("inputs", "outputs"):
        spec = entry.get(kind)
        if not isinstance(spec, dict):
            raise ManifestError(f"{where}.{kind} must be an object name -> {{dtype, shape}}")
        for io_name, dtype in required[kind].items():
            got = spec.get(io_name)
            if not isinstance(got, dict):
                raise ManifestError(f"{where}.{kind} lacks {io_name!r} (has {sorted(spec)}); "
                                    f"this runtime feeds/reads {sorted(required[kind])}")
            if got.get("dtype") != dtype:
                raise ManifestError(f"{where}.{kind}.{io_name}: dtype {got.get('dtype')!r}, "
                                    f"expected {dtype!r}")
        io[kind] = MappingProxyType({k: MappingProxyType(dict(v)) if isinstance(v, dict) else v
                                     for k, v in spec.items()})
    return GraphEntry(name=name, path=resolved, sha256=digest.lower(), inputs=io["inputs"],
                      outputs=io["outputs"])


def _check_digest(entry: GraphEntry, digest: str) -> None:
    if digest != entry.sha256:
        raise ModelIntegrityError(f"{entry.path}: sha256 {digest[:16]}... does not match the "
                                  f"manifest's {entry.sha256[:16]}... (the {entry.name} graph was "
                                  f"modified or truncated after export; re-export the model)")

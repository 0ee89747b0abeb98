"""Read and check ``iris.json``, the manifest that ``iris-export`` writes next to the two graphs.

The manifest is the only thing the runtime knows about a model: the format tag and version, the
model's config, its image size, the ray sampling (near, far, samples), and per graph the file
name, its sha256 and its I/O spec (the names and dtypes of ``export/io_spec.py``, copied into the
manifest so that the runtime never imports ``export`` or torch).

Checks, each failing with a typed ``ModelFileError`` that names the file and what was expected:

- ``ManifestError``: ``iris.json`` missing, not JSON, a field missing or of the wrong type, a
  graph path that is absolute, contains ``..`` or resolves (through symlinks) outside the model
  directory, or an I/O spec that lacks a name the runtime feeds or reads;
- ``ModelFormatError``: format name other than ``"iris-model"`` or a version other than 1;
- ``ModelIntegrityError``: a graph file whose sha256 differs from the manifest's (tampered,
  truncated or replaced); a missing graph file is a plain ``ModelFileError``.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath, PureWindowsPath
from types import MappingProxyType
from typing import Any, Mapping

from .errors import ManifestError, ModelFileError, ModelFormatError, ModelIntegrityError

MANIFEST_NAME = "iris.json"
FORMAT_NAME = "iris-model"
FORMAT_VERSION = 1
#: Version of the graphs' I/O names and layouts (export/io_spec.py IO_SPEC_VERSION).
IO_SPEC_VERSION = 1

#: The names the runtime feeds and reads, with their dtypes (export/io_spec.py is the source;
#: the manifest carries it, and a model whose spec lacks one of these cannot be run).
REQUIRED_IO: dict[str, dict[str, dict[str, str]]] = {
    "encoder": {
        "inputs": {"images": "float32"},
        "outputs": {"field_maps": "float32", "world_from_cam": "float32", "focal": "float32"},
    },
    "renderer": {
        "inputs": {"field_maps": "float32", "grid": "float32", "cues": "float32", "mask": "bool",
                   "positions": "float32", "directions": "float32"},
        "outputs": {"rgb": "float32", "weights": "float32"},
    },
}

_CHUNK = 1 << 20


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
    graphs: Mapping[str, GraphEntry]
    raw: Mapping[str, Any] = field(repr=False)  # the whole document, for reports

    @property
    def field_channels(self) -> int | None:
        """C' of the field maps: the manifest's ``field_channels``, else from the config
        (field_width * (1 + 2 * view_blocks)); None when neither says."""
        value = self.raw.get("field_channels")
        if isinstance(value, int) and not isinstance(value, bool) and value > 0:
            return value
        try:
            return int(self.config["field_width"]) * (1 + 2 * int(self.config["view_blocks"]))
        except (KeyError, TypeError, ValueError):
            return None


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def read_graph_bytes(entry: GraphEntry) -> bytes:
    """The graph file's bytes, checked against the manifest's sha256 (what a session is built from,
    so the graph that runs is the graph that was checked, even if the file changes later)."""
    try:
        data = entry.path.read_bytes()
    except FileNotFoundError:
        raise ModelFileError(f"{entry.path}: {entry.name} graph file is missing") from None
    except OSError as exc:
        raise ModelFileError(f"{entry.path}: cannot read the {entry.name} graph: {exc}") from None
    _check_digest(entry, hashlib.sha256(data).hexdigest())
    return data


def read_manifest(model_dir: str | os.PathLike, *, verify_hashes: bool = True) -> Manifest:
    """Read ``model_dir/iris.json`` and check it (see the module docstring); with
    ``verify_hashes`` also hash each graph file against the manifest."""
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise ModelFileError(f"model directory {str(model_dir)!r}: no such directory "
                             f"(expected the output directory of iris-export)")
    path = model_dir / MANIFEST_NAME
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ManifestError(f"{path}: no such file (expected the {MANIFEST_NAME} manifest written "
                            f"by iris-export)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ManifestError(f"{path}: cannot read: {exc}") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ManifestError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise ManifestError(f"{path}: expected a JSON object at the top level")

    fmt, version = doc.get("format"), doc.get("version")
    if fmt != FORMAT_NAME:
        raise ModelFormatError(f"{path}: format {fmt!r}, expected {FORMAT_NAME!r} "
                               f"(the manifest of an iris-export model directory)")
    if version != FORMAT_VERSION or isinstance(version, bool):
        raise ModelFormatError(f"{path}: {FORMAT_NAME} version {version!r}; this runtime reads "
                               f"version {FORMAT_VERSION} (re-export the model with a matching "
                               f"iris-export, or upgrade iris_runtime)")

    io_version = doc.get("io_spec_version", IO_SPEC_VERSION)
    if io_version != IO_SPEC_VERSION:
        raise ModelFormatError(f"{path}: I/O spec version {io_version!r}; this runtime feeds I/O "
                               f"spec version {IO_SPEC_VERSION}")

    config = doc.get("config", {})
    if not isinstance(config, dict):
        raise ManifestError(f"{path}: 'config' must be an object, got {type(config).__name__}")

    def number(key, cfg_key=None, kind=float):
        value = doc.get(key, config.get(cfg_key or key))
        ok = (isinstance(value, (int, float)) and not isinstance(value, bool)
              and math.isfinite(value))
        if kind is int:
            ok = ok and float(value).is_integer() and value > 0
        if not ok:
            what = "a positive integer" if kind is int else "a finite number"
            raise ManifestError(f"{path}: {key!r} must be {what}, got {value!r}")
        return kind(value)

    size = doc.get("image_size", [config.get("image_height"), config.get("image_width")])
    if (not isinstance(size, (list, tuple)) or len(size) != 2
            or not all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size)):
        raise ManifestError(f"{path}: 'image_size' must be [height, width] positive integers, "
                            f"got {size!r}")
    near, far = number("near"), number("far")
    if not 0 < near < far:
        raise ManifestError(f"{path}: need 0 < near < far, got near={near}, far={far}")
    samples = number("samples", kind=int)

    graphs_doc = doc.get("graphs")
    if not isinstance(graphs_doc, dict):
        raise ManifestError(f"{path}: 'graphs' must be an object with 'encoder' and 'renderer'")
    root = model_dir.resolve()
    graphs = {}
    for name, required in REQUIRED_IO.items():
        entry = graphs_doc.get(name)
        if not isinstance(entry, dict):
            raise ManifestError(f"{path}: graphs.{name} missing (expected an object with 'file', "
                                f"'sha256', 'inputs', 'outputs')")
        graphs[name] = _graph_entry(path, root, name, entry, required)
    # Variants of a graph (e.g. "renderer_int8", written by iris-export --quantize int8) have the
    # I/O of the graph they stand in for.
    for name, entry in graphs_doc.items():
        base = entry.get("variant_of") if isinstance(entry, dict) else None
        if name not in graphs and base in REQUIRED_IO:
            graphs[name] = _graph_entry(path, root, name, entry, REQUIRED_IO[base])

    manifest = Manifest(model_dir=root, version=version, config=MappingProxyType(dict(config)),
                        image_size=(int(size[0]), int(size[1])), near=near, far=far,
                        samples=samples, graphs=MappingProxyType(graphs),
                        raw=MappingProxyType(doc))
    if verify_hashes:
        for entry in graphs.values():
            if not entry.path.is_file():
                raise ModelFileError(f"{entry.path}: {entry.name} graph file is missing "
                                     f"(listed in {path})")
            _check_digest(entry, sha256_file(entry.path))
    return manifest


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
        if spec is None and isinstance(entry.get("io"), dict):
            spec = entry["io"].get(kind)
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

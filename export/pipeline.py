"""``export_model``: checkpoint (or built model) -> validated ``OUT_DIR`` with two graphs + manifest.

Stages: load the checkpoint (``iris_train.load_model``, ``weights_only=True``), export the encoder
and the renderer (``export.graphs``), optionally quantise the renderer to int8, validate everything
against torch (``export.validate``), write ``iris.json`` (``export.manifest``). All of it happens
in a fresh hidden directory next to ``OUT_DIR`` that is renamed to ``OUT_DIR`` only at the end: a
failure at any stage (bad checkpoint, export error, validation beyond tolerance, Ctrl-C) leaves
``OUT_DIR`` as it was and removes the temporary directory.
"""
from __future__ import annotations

import os
import shutil
import sys
import threading
import time
import uuid
from pathlib import Path

import onnx

from iris_runtime.fileio import sha256_file
from iris_runtime.manifest import camera_name
from iris_runtime.validation import check_integer
from iris_train.model import CheckpointError, IrisModel, load_model, read_checkpoint, trained_cameras

from . import io_spec
from .errors import ExportArgumentError, ExportError, OutputExistsError
from .fast_renderer import RENDERER_KINDS, SelectedViewsRendererGraph, renderer_wrapper
from .graphs import DEFAULT_OPSET, EXPORTER, RendererGraph, check_opset, export_graph, quantize_int8
from .manifest import MANIFEST_NAME, build_manifest, graph_entry, write_manifest
from .validate import validate

QUANTIZE_CHOICES = ("int8",)
INT8_FILE = "renderer.int8.onnx"


def _load(path: Path) -> IrisModel:
    try:
        return load_model(path)
    except CheckpointError:
        raise
    except Exception as exc:    # a well-formed dict whose contents load_model did not foresee
        raise CheckpointError(f"checkpoint {str(path)!r} could not be loaded: {type(exc).__name__}: "
                              f"{str(exc).splitlines()[0][:200] if str(exc) else ''}") from None


def _publish(tmp: Path, out_dir: Path, force: bool) -> None:
    """Rename ``tmp`` to ``out_dir``; with ``force`` an existing ``out_dir`` is moved aside first
    and deleted only once the new one is in place (restored if the rename fails)."""
    if not out_dir.exists() and not out_dir.is_symlink():
        os.rename(tmp, out_dir)
        return
    if not force:
        raise OutputExistsError(f"output {str(out_dir)!r} already exists (use --force to replace it)")
    old = out_dir.with_name(f".{out_dir.name}.old-{uuid.uuid4().hex[:8]}")
    os.rename(out_dir, old)
    try:
        os.rename(tmp, out_dir)
    except BaseException:
        os.rename(old, out_dir)
        raise
    if old.is_dir() and not old.is_symlink():
        shutil.rmtree(old)
    else:
        old.unlink()


def _default_cameras(cameras: str | None, trained: str, distilled: bool = False) -> str:
    """The manifest's "cameras": ``cameras`` when given (the trained ones, or "refined" over a
    renderer trained with "solve"); else "refined" over a renderer trained with "solve"
    whose camera head was ``distilled`` from the solve's cameras (``scripts/head_distill.py``: a
    head trained to start the refinement, which is then as accurate as the solve in a fraction
    of its time, docs/CAMERAS.md), else ``trained``; ``ExportArgumentError`` otherwise."""
    if cameras is None:
        return "refined" if distilled and trained == "solve" else trained
    if cameras == trained:
        return trained
    if cameras == "refined" and trained == "solve":
        return cameras
    raise ExportArgumentError(f"cameras: this renderer was trained with {trained!r} cameras, so "
                              f"the default can be {trained!r}"
                              + (" or 'refined'" if trained == "solve" else "")
                              + f", not {cameras!r}")


def export_model(model_or_ckpt: IrisModel | str | os.PathLike, out_dir: str | os.PathLike, *,
                 opset: int = DEFAULT_OPSET, quantize: str | None = None, force: bool = False,
                 progress: bool = True, quick: bool = False, threads: int | None = None,
                 renderer: str = "fast", cameras: str | None = None) -> Path:
    """Export ``model_or_ckpt`` to ``out_dir/{encoder.onnx, renderer.onnx, iris.json}`` (and, for
    the "fast" renderer graphs, ``renderer_views.onnx``: the renderer on per-point pre-selected
    views, ``io_spec.RENDERER_VIEWS``, which ``top_k_by="point"`` renders with; for a model whose
    camera head has an encoder of its own, ``encoder_cameras.onnx``: its cameras alone,
    ``io_spec.ENCODER_CAMERAS``, which the runtime runs where it needs no field maps).

    ``model_or_ckpt``: an ``IrisModel`` or a checkpoint path. ``opset``: ONNX opset (>= 18).
    ``quantize="int8"`` adds ``renderer.int8.onnx`` (dynamic int8; its error is recorded, not
    enforced). ``force`` replaces an existing ``out_dir``. ``progress`` prints one line per stage
    to stderr. ``quick`` shrinks the validation probes (tests); ``threads`` sets the intra-op
    threads of ONNX Runtime and torch during validation (see ``export.validate.validate``).
    ``cameras``: the manifest's "cameras", the runtime's default (None: "refined" where the
    renderer was trained with "solve" and the checkpoint's camera head distilled from the
    solve, else the cameras the renderer was trained with, ``trained_cameras``); "refined" (the
    camera head's refined by the photos) only for a renderer trained with "solve", whose unit
    the refinement gives.
    ``renderer``: which renderer graph to write (``export.fast_renderer.RENDERER_KINDS``):
    "fast" (the default) or "fast-contrib" (``FastRendererGraph``: same I/O and values, laid
    out for ONNX Runtime's CPU kernels) or "reference" (``RendererGraph``, the model's
    ``render_samples`` traced as is); each validated against the same torch reference and
    recorded as ``export.renderer_graph``. Frame times: docs/PERFORMANCE.md.
    Returns ``out_dir``.

    Raises ``OutputExistsError`` (``out_dir`` exists, no ``force``), ``CheckpointError``
    (unreadable checkpoint), ``ExportArgumentError``, ``ValidationError`` (ONNX Runtime vs torch
    beyond tolerance); in every case ``out_dir`` is left untouched.
    """
    t0 = time.perf_counter()
    out_dir = Path(out_dir).absolute()
    threads = _check_arguments(out_dir, opset, quantize, renderer, threads, force)

    say = _Progress(t0) if progress else _Progress(None)
    try:
        model, source, trained, distilled = _model_and_source(model_or_ckpt, say)
        cameras = _default_cameras(camera_name(cameras), trained, distilled)
        was_training = model.training
        model.eval()

        out_dir.parent.mkdir(parents=True, exist_ok=True)
        tmp = out_dir.with_name(f".{out_dir.name}.tmp-{uuid.uuid4().hex[:8]}")
        tmp.mkdir()
        try:
            files, entries = _export_graphs(model, tmp, opset, renderer, quantize, say)
            say(f"validating against torch ({'quick' if quick else 'full'} probes)")
            report = validate(model, files, quick=quick, threads=threads, progress=say)
            graphs = _graph_entries(model, files, entries)
            unexpected = sorted({p.name for p in tmp.iterdir()} - {p.name for p in files.values()})
            if unexpected:     # e.g. a side .data file: the graphs must be self-contained
                raise ExportError(f"unexpected files next to the graphs: {unexpected}")
            ir_version = onnx.load_model(str(files["encoder"]), load_external_data=False).ir_version
            manifest = build_manifest(model.cfg, graphs, report, opset=opset, ir_version=ir_version,
                                      exporter=EXPORTER, source=source, cameras=cameras,
                                      renderer_sampler=RendererGraph(model).sampler,
                                      renderer_graph=renderer)
            write_manifest(tmp / MANIFEST_NAME, manifest)
            _publish(tmp, out_dir, force)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        finally:
            model.train(was_training)
        say(f"wrote {out_dir} ({', '.join(sorted(p.name for p in out_dir.iterdir()))})")
        return out_dir
    finally:
        say.close()


class _Progress:
    """``say(msg)``: a progress line on stderr, and while a step runs silently (one
    ``torch.onnx.export`` takes half a minute on 2 cores) a line every ``EVERY`` seconds saying
    it still runs, so that a log shows life. ``t0`` None: silent."""
    EVERY = 10.0

    def __init__(self, t0: float | None):
        self.t0, self.step = t0, ""
        self.last = self.since = time.perf_counter()
        self.stop = threading.Event()
        self.thread = None
        if t0 is not None:
            self.thread = threading.Thread(target=self._beat, name="iris-export-progress",
                                           daemon=True)
            self.thread.start()

    def _print(self, msg: str) -> None:
        self.last = time.perf_counter()
        print(f"iris-export [{self.last - self.t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    def __call__(self, msg: str) -> None:
        if self.t0 is not None:
            self.step, self.since = msg, time.perf_counter()
            self._print(msg)

    def _beat(self) -> None:
        while not self.stop.wait(1.0):
            now = time.perf_counter()
            if now - self.last >= self.EVERY and self.step:
                self._print(f"... working, {now - self.since:.0f} s since: {self.step}")

    def close(self) -> None:
        self.stop.set()
        if self.thread is not None:
            self.thread.join()


def _check_arguments(out_dir: Path, opset, quantize, renderer, threads, force) -> int | None:
    """``export_model``'s options checked before anything is loaded or written -> ``threads``."""
    check_opset(opset)
    if quantize not in (None, *QUANTIZE_CHOICES):
        raise ExportArgumentError(f"quantize: expected one of {list(QUANTIZE_CHOICES)} or None, "
                                  f"got {quantize!r}")
    if renderer not in RENDERER_KINDS:
        raise ExportArgumentError(f"renderer: expected one of {list(RENDERER_KINDS)}, got "
                                  f"{renderer!r}")
    threads = check_integer(threads, "threads", allow_none=True, error=ExportArgumentError)
    if (out_dir.exists() or out_dir.is_symlink()) and not force:
        raise OutputExistsError(f"output {str(out_dir)!r} already exists (use --force to replace it)")
    return threads


def _model_and_source(model_or_ckpt, say) -> tuple[IrisModel, dict, str, bool]:
    """The model to export -> ``(model, source, trained, distilled)``: the manifest's "source"
    (the checkpoint's name and sha256), the cameras its renderer was trained with
    (``trained_cameras``; "model" for a model given as such) and whether its camera head was
    distilled from the solve."""
    if not isinstance(model_or_ckpt, (IrisModel, str, os.PathLike)):
        raise ExportArgumentError(f"model_or_ckpt: expected an IrisModel or a checkpoint path, got "
                                  f"{type(model_or_ckpt).__name__}")
    if isinstance(model_or_ckpt, IrisModel):
        return model_or_ckpt, {"checkpoint": None}, "model", False
    ckpt = Path(model_or_ckpt)
    say(f"loading checkpoint {ckpt}")
    model = _load(ckpt)
    source = {"checkpoint": ckpt.name, "sha256": sha256_file(ckpt)}
    payload = read_checkpoint(ckpt)
    return model, source, trained_cameras(payload), "distill" in payload


def _export_graphs(model: IrisModel, tmp: Path, opset: int, renderer: str, quantize, say):
    """Every graph of ``model`` written to ``tmp`` -> ``(files, entries)`` by graph name: the
    encoder, the renderer of kind ``renderer``, the selected-views renderer (fast kinds), the
    camera graph (a camera head with its own encoder) and the int8 renderer (``quantize``)."""
    files, entries = {}, {}
    for graph in ("encoder", "renderer"):
        spec = io_spec.GRAPHS[graph]
        say(f"exporting {graph} ({EXPORTER}, opset {opset})")
        alt = {"wrapper": renderer_wrapper(model, renderer)} \
            if graph == "renderer" and renderer != "reference" else {}
        result = export_graph(model, graph, tmp / spec["file"], opset, **alt)
        say(f"exported {graph}: {result.nodes} nodes, {result.path.stat().st_size / 1e6:.1f} MB "
            f"in {result.seconds:.1f} s")
        files[graph], entries[graph] = result.path, result
    if renderer != "reference":    # per-point pre-selected views (top_k_by="point")
        spec = io_spec.spec_for("renderer_views", model.cfg.explicit_rgb)
        say("exporting renderer_views (per-point pre-selected views)")
        result = export_graph(model, "renderer_views", tmp / spec["file"], opset,
                              wrapper=SelectedViewsRendererGraph(
                                  model, contrib=renderer == "fast-contrib"))
        say(f"exported renderer_views: {result.nodes} nodes in {result.seconds:.1f} s")
        files["renderer_views"], entries["renderer_views"] = result.path, result
    if model.camera_encoder is not None:     # cameras without the field's encoder
        spec = io_spec.spec_for("encoder_cameras")
        say("exporting encoder_cameras (the camera head on its own encoder)")
        result = export_graph(model, "encoder_cameras", tmp / spec["file"], opset)
        say(f"exported encoder_cameras: {result.nodes} nodes in {result.seconds:.1f} s")
        files["encoder_cameras"], entries["encoder_cameras"] = result.path, result
    if quantize == "int8":
        result = quantize_int8(files["renderer"], tmp / INT8_FILE)
        say(f"quantised renderer to int8: {result.nodes} nodes, "
            f"{result.path.stat().st_size / 1e6:.1f} MB in {result.seconds:.1f} s")
        files["renderer_int8"], entries["renderer_int8"] = result.path, result
    return files, entries


def _graph_entries(model: IrisModel, files: dict, entries: dict) -> dict:
    """The manifest's "graphs": each file's entry (``manifest.graph_entry``); a variant (int8)
    names its base graph and has no tolerance (measured and recorded, not enforced)."""
    graphs = {}
    for name, path in files.items():
        base = io_spec.base_graph(name)
        extra = {"variant_of": base, "precision": "int8",
                 "quantization": "onnxruntime.quantization.quantize_dynamic(weight_type=QInt8)"} \
            if name != base else {"precision": "float32"}
        graphs[name] = graph_entry(path, io_spec.spec_for(base, model.cfg.explicit_rgb),
                                   entries[name].nodes, **extra)
        if name != base:          # measured and recorded, but not held to the fp32 tolerance
            graphs[name]["tolerance"] = None
    return graphs

__all__ = ["export_model", "QUANTIZE_CHOICES", "INT8_FILE"]

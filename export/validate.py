"""Validation of the exported graphs: the ONNX checker, then ONNX Runtime against torch.

``validate(model, files)`` runs, for each graph:

1. ``onnx.checker.check_model(full_check=True)`` (strict shape inference included);
2. the I/O contract: ONNX Runtime's input/output names, dtypes and axes equal the I/O spec
   (``iris_runtime.io_spec``);
3. probe inputs through ONNX Runtime and through the torch reference, max abs error per output
   against the spec's tolerance (read from ``io_spec`` at call time), on the probes of
   ``export.probes`` (what each probe is and what its reference is). Non-finite outputs and
   wrong shapes count as an infinite error.
3b. encoder isolation inside ONNX Runtime: for each probe with queries, the references' outputs
   (field maps, cameras, focal) with the queries present, with other query images, and with no
   queries at all; max abs difference against ``io_spec.ENCODER["isolation_tolerance"]`` (1e-6;
   the rows are computed identically, docs/PERFORMANCE.md "Reference isolation").
4. the median time of each graph in ONNX Runtime and in torch on a fixed input (renderer: R=1024,
   S=cfg.samples, V'=4; ``quick`` shrinks probes and timing for tests).

An error above tolerance raises ``ValidationError`` naming the graph, the output, the error reached
and the tolerance. An int8 renderer (``files["renderer_int8"]``) goes through the same renderer
probes, but its error is only recorded, never enforced.
"""
from __future__ import annotations

import math
import statistics
import time
from pathlib import Path
from typing import Callable

import numpy as np
import onnx
import onnxruntime as ort
import torch

from iris_train.model import IrisModel

from . import io_spec
from .errors import ValidationError
from .fast_renderer import SelectedViewsRendererGraph
from .graphs import EncoderCamerasGraph, EncoderGraph, RendererGraph, fixed_dims
# The probes' names stay importable from here (tests and benchmarks import them so).
from .probes import (PROBE_SEED, QUERY_COUNTS, VIEW_COUNTS, Probe, encoder_probes,
                     random_renderer_inputs, renderer_inputs, renderer_probes,
                     renderer_views_probes, scene_images, scene_rays, selected_view_inputs,
                     to_numpy)

_ORT_TYPES = {"float32": "tensor(float)", "bool": "tensor(bool)", "int64": "tensor(int64)"}


# -- running and comparing ----------------------------------------------------------------------
def max_abs_error(got: np.ndarray, want: np.ndarray) -> float:
    """Max abs difference; ``inf`` on a shape mismatch or a non-finite value on either side."""
    got, want = np.asarray(got), np.asarray(want)
    if got.shape != want.shape or not (np.isfinite(got).all() and np.isfinite(want).all()):
        return math.inf
    if got.size == 0:
        return 0.0
    return float(np.max(np.abs(got.astype(np.float64) - want.astype(np.float64))))


def isolation_errors(sess: ort.InferenceSession, probes: list[Probe]) -> dict[str, float]:
    """Max abs difference, inside ONNX Runtime, between the references' outputs of each probe with
    queries (references first) and the same references run with other query images (1 - images)
    and with no queries at all. 0 when no probe has queries."""
    names = [o.name for o in sess.get_outputs()]
    worst = {n: 0.0 for n in names}
    for probe in probes:
        V = probe.info.get("references")
        if not V:
            continue
        images = to_numpy(probe.inputs["images"])
        is_reference = to_numpy(probe.inputs["is_reference"])
        changed = images.copy()
        changed[V:] = 1.0 - changed[V:]
        base = sess.run(names, {"images": images, "is_reference": is_reference})
        for feed in ({"images": changed, "is_reference": is_reference},
                     {"images": np.ascontiguousarray(images[:V]), "is_reference": is_reference[:V]}):
            other = sess.run(names, feed)
            for n, a, b in zip(names, base, other):
                rows = slice(None) if n == "focal" else slice(0, V)
                worst[n] = max(worst[n], max_abs_error(a[rows], b[rows]))
    return worst


def session(path: str | Path, graph: str, threads: int | None = None) -> ort.InferenceSession:
    """A plain CPU session (onnxruntime's default in-memory optimisations, nothing saved)."""
    options = ort.SessionOptions()
    options.log_severity_level = 3
    if threads:
        options.intra_op_num_threads = threads
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:
        raise ValidationError(f"{graph}: onnxruntime {ort.__version__} cannot load {Path(path).name}: "
                              f"{str(exc).splitlines()[0][:300]}", graph=graph) from None


def check_graph_file(path: str | Path, graph: str) -> None:
    """``onnx.checker.check_model(full_check=True)``; a failure is a ``ValidationError``."""
    try:
        onnx.checker.check_model(str(path), full_check=True)
    except Exception as exc:
        raise ValidationError(f"{graph}: onnx checker rejects {Path(path).name}: "
                              f"{str(exc).splitlines()[0][:300]}", graph=graph) from None


def check_io(sess: ort.InferenceSession, spec: dict, dims: dict[str, int], graph: str) -> None:
    """ONNX Runtime's view of the graph's inputs and outputs equals the spec (names, order,
    dtypes, fixed axes, dynamic axis names)."""
    for kind, got in (("inputs", sess.get_inputs()), ("outputs", sess.get_outputs())):
        want = spec[kind]
        if [a.name for a in got] != list(want):
            raise ValidationError(f"{graph}: {kind} {[a.name for a in got]} differ from the I/O spec "
                                  f"{list(want)}", graph=graph)
        for arg in got:
            entry = want[arg.name]
            shape = [dims.get(d, d) for d in entry["shape"]]
            if arg.type != _ORT_TYPES[entry["dtype"]] or list(arg.shape) != shape:
                raise ValidationError(f"{graph}: {arg.name} is {arg.type} {arg.shape}, the I/O spec says "
                                      f"{entry['dtype']} {shape}", graph=graph, output=arg.name)


def run_probes(sess: ort.InferenceSession, probes: list[Probe]) -> list[dict]:
    names = [o.name for o in sess.get_outputs()]
    rows = []
    for probe in probes:
        outputs = sess.run(names, {k: to_numpy(v) for k, v in probe.inputs.items()})
        errors = {n: max_abs_error(o, probe.reference[n]) for n, o in zip(names, outputs)}
        rows.append({"probe": probe.name, **probe.info, "max_abs_error": errors})
    return rows


def summarise(graph: str, rows: list[dict], tolerance: dict[str, float], enforce: bool) -> dict:
    """Worst error per output over the probes, compared with the tolerance; raise if enforced."""
    worst, worst_probe = {}, {}
    for row in rows:
        for out, err in row["max_abs_error"].items():
            if out not in worst or not err <= worst[out]:       # NaN-proof
                worst[out], worst_probe[out] = err, row["probe"]
    passed = all(worst[o] <= tol for o, tol in tolerance.items())
    if enforce and not passed:
        out = max(tolerance, key=lambda o: math.inf if not worst[o] <= tolerance[o] else -1.0)
        err, tol = worst[out], tolerance[out]
        raise ValidationError(f"{graph} output {out!r}: max abs error {err:.3g} exceeds the tolerance "
                              f"{tol:.3g} (probe {worst_probe[out]!r}); nothing was written",
                              graph=graph, output=out, error=err, tolerance=tol,
                              probe=worst_probe[out])
    return {"max_abs_error": worst, "tolerance": dict(tolerance), "passed": passed,
            "enforced": enforce, "probes": rows}


def _check_isolation(graph: str, errors: dict[str, float], tolerance: float, enforce: bool) -> dict:
    worst = max(errors, key=lambda o: math.inf if not errors[o] <= tolerance else errors[o])
    passed = errors[worst] <= tolerance
    if enforce and not passed:
        raise ValidationError(f"{graph}: the references' output {worst!r} changes by "
                              f"{errors[worst]:.3g} when queries are added, changed or removed "
                              f"(isolation tolerance {tolerance:.3g}); nothing was written",
                              graph=graph, output=worst, error=errors[worst], tolerance=tolerance,
                              probe="isolation")
    return {"max_abs_error": errors, "tolerance": tolerance, "passed": passed}


def median_time(fn: Callable[[], object], runs: int) -> float:
    """Median wall time of ``runs`` calls after one warm-up call (the first call also pays for
    allocations and lazy initialisation)."""
    fn()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def time_graph(sess: ort.InferenceSession, torch_fn: Callable, inputs: dict[str, torch.Tensor],
               runs: int, t_torch: float | None = None) -> dict:
    """Median times of the session and of the torch reference (unless ``t_torch`` is known)."""
    feed = {k: to_numpy(v) for k, v in inputs.items()}
    t_ort = median_time(lambda: sess.run(None, feed), runs)
    if t_torch is None:
        with torch.no_grad():
            t_torch = median_time(lambda: torch_fn(**inputs), runs)
    return {"inputs": {k: list(v.shape) for k, v in inputs.items()}, "runs": runs,
            "onnxruntime_median_s": round(t_ort, 6), "torch_median_s": round(t_torch, 6),
            "ort_over_torch": round(t_ort / t_torch, 4)}


def validate(model: IrisModel, files: dict[str, str | Path], *, quick: bool = False,
             threads: int | None = None, progress: Callable[[str], None] | None = None) -> dict:
    """Validate ``files`` (``{"encoder": path, "renderer": path[, "renderer_int8": path]
    [, "renderer_views": path][, "encoder_cameras": path]}``)
    exported from ``model``; return the report for the manifest, or raise ``ValidationError``.

    ``threads``: intra-op threads of ONNX Runtime and torch while validating (default: each
    library's own default). On a machine shared with other jobs, 1 is much faster: both libraries
    spin-wait for their worker threads (docs/PERFORMANCE.md, "Renderer and encoder graphs").
    """
    torch_threads, was_training = torch.get_num_threads(), model.training
    if threads:
        torch.set_num_threads(threads)
    try:
        return _validate(model.eval(), files, quick=quick, threads=threads, progress=progress)
    finally:
        torch.set_num_threads(torch_threads)
        model.train(was_training)


def _validate(model, files, *, quick, threads, progress) -> dict:
    say = progress or (lambda msg: None)
    cfg = model.cfg
    dims = fixed_dims(cfg)
    n_rays = 16 if quick else 128
    runs = 2 if quick else 5
    timing = {"encoder": {"images": scene_images(4, cfg.image_height, cfg.image_width,
                                                 torch.Generator().manual_seed(PROBE_SEED)),
                          "is_reference": torch.ones(4, dtype=torch.bool)},
              "renderer": random_renderer_inputs(model, 4, 64 if quick else 1024, cfg.samples,
                                                 torch.Generator().manual_seed(PROBE_SEED))}
    torch_fns = {"encoder": EncoderGraph(model).eval(), "renderer": RendererGraph(model).eval()}
    if "encoder_cameras" in files:
        timing["encoder_cameras"] = timing["encoder"]
        torch_fns["encoder_cameras"] = EncoderCamerasGraph(model).eval()
    if "renderer_views" in files:
        timing["renderer_views"] = selected_view_inputs(
            timing["renderer"], 2, torch.Generator().manual_seed(PROBE_SEED))[0]
        torch_fns["renderer_views"] = SelectedViewsRendererGraph(model).eval()
    report = {"quick": quick, "probe_seed": PROBE_SEED, "torch_threads": torch.get_num_threads(),
              "onnxruntime_threads": threads or "default"}
    probes: dict[str, list[Probe]] = {}
    for graph in files:
        base = io_spec.base_graph(graph)
        spec = io_spec.spec_for(base, cfg.explicit_rgb)
        start = time.perf_counter()
        check_graph_file(files[graph], graph)
        sess = session(files[graph], graph, threads)
        check_io(sess, spec, dims, graph)
        # The camera graph answers the encoder's probes (its outputs are a subset).
        kind = "encoder" if base == "encoder_cameras" else base
        if kind not in probes:
            probes[kind] = (encoder_probes(model) if kind == "encoder" else
                            (renderer_views_probes if kind == "renderer_views"
                             else renderer_probes)(model, n_rays=n_rays))
        enforce = graph == base
        entry = summarise(graph, run_probes(sess, probes[kind]), spec["tolerance"], enforce)
        if kind == "encoder":
            entry["isolation"] = _check_isolation(graph, isolation_errors(sess, probes[kind]),
                                                  spec["isolation_tolerance"], enforce)
        known = report[base]["time"]["torch_median_s"] if base in report else None
        entry["time"] = time_graph(sess, torch_fns[base], timing[base], runs, known)
        report[graph] = entry
        errors = ", ".join(f"{o} {e:.2g}" for o, e in entry["max_abs_error"].items())
        say(f"validated {graph}: {len(probes[kind])} probes, max abs error {errors}"
            f"{'' if enforce else ' (recorded, not enforced)'}; onnxruntime "
            f"{entry['time']['onnxruntime_median_s'] * 1e3:.1f} ms vs torch "
            f"{entry['time']['torch_median_s'] * 1e3:.1f} ms ({time.perf_counter() - start:.1f} s)")
    return report


__all__ = ["validate", "ValidationError", "Probe", "scene_images", "renderer_inputs",
           "random_renderer_inputs", "selected_view_inputs", "scene_rays", "encoder_probes",
           "renderer_probes", "renderer_views_probes",
           "isolation_errors", "QUERY_COUNTS",
           "max_abs_error", "check_graph_file", "check_io", "session", "median_time", "VIEW_COUNTS"]

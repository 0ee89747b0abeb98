"""Op layouts in ONNX Runtime on the renderer's shapes, each against the form the fast renderer
graph uses instead (the facts behind ``export.fast_renderer``):

* reductions over the leading (view) axis: ``ReduceSum`` against ``MatMul`` with a ones row
  (``_sum_views``), ``ReduceMax`` against a ``Scan`` of ``Max`` (``views_max_as_scan``);
* broadcasts over a trailing axis of 1 (``x [V, N, 1] * y [V, N, 3]``, the tent's
  ``g [V, N, 1] - centres [8]``, the position encoding's ``p [N, 3, 1] * freqs [F]``) against a
  matmul that makes the same values (``_expand``, ``_tent_axes``, ``select_pos_freqs``);
* the ray attention's per-head projections 16 wide against 17 wide (why the key mask stays an Add);
* exact GELU (ONNX, contrib, written with Erf) and Add + LayerNormalization against the contrib
  SkipLayerNormalization (the kernels most of the non-matmul time is in).

    python benchmarks/ort_reductions.py [--shape 5,6528,64 --threads 2 --runs 50]

One-node graphs built with ``onnx.helper``; median (and min) of ``--runs`` calls after one warm-up,
spinning off (no session spins while another runs). Needs numpy, onnx, onnxruntime.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper


def session(nodes, initializers, threads: int, inputs=("x",)) -> ort.InferenceSession:
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info(n, TensorProto.FLOAT,
                                                                         None) for n in inputs],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
                              initializer=initializers)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 20),
                                                    helper.make_opsetid("com.microsoft", 1)])
    model.ir_version = 9
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    opts.log_severity_level = 3
    return ort.InferenceSession(model.SerializeToString(), opts,
                                providers=["CPUExecutionProvider"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shape", default="5,6528,64", help="V,N,C")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs", type=int, default=50)
    args = ap.parse_args(argv)
    V, N, C = (int(x) for x in args.shape.split(","))
    x = np.random.default_rng(0).random((V, N, C), dtype=np.float32)
    axis0 = numpy_helper.from_array(np.array([0], np.int64), "axis0")
    flat = numpy_helper.from_array(np.array([V, -1], np.int64), "flat")
    ones = numpy_helper.from_array(np.ones((1, V), np.float32), "ones")
    rng = np.random.default_rng(0)
    c = lambda a, name: numpy_helper.from_array(np.asarray(a), name)           # noqa: E731
    zero = c(np.array(0, np.int64), "zero")
    scan_body = helper.make_graph(
        [helper.make_node("Max", ["acc", "xi"], ["acc_out"])], "body",
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, ["n", "c"]) for n in ("acc", "xi")],
        [helper.make_tensor_value_info("acc_out", TensorProto.FLOAT, ["n", "c"])])
    # (name, nodes, initializers, feed, expected)
    cases = [
        ("ReduceSum(axis 0)", [helper.make_node("ReduceSum", ["x", "axis0"], ["y"], keepdims=0)],
         [axis0], {"x": x}, x.sum(0)),
        ("MatMul(ones[1,V], x[V,-1])", [helper.make_node("Reshape", ["x", "flat"], ["x2"]),
                                        helper.make_node("MatMul", ["ones", "x2"], ["y"])],
         [flat, ones], {"x": x}, x.sum(0)),
        ("ReduceMax(axis 0)", [helper.make_node("ReduceMax", ["x", "axis0"], ["y"], keepdims=0)],
         [axis0], {"x": x}, x.max(0)),
        ("Scan(Max) over axis 0", [helper.make_node("Gather", ["x", "zero"], ["x0"], axis=0),
                                   helper.make_node("Scan", ["x0", "x"], ["y"],
                                                    num_scan_inputs=1, body=scan_body)],
         [zero], {"x": x}, x.max(0)),
        ("Add(x, x) (one same-shape pass)", [helper.make_node("Add", ["x", "x"], ["y"])], [],
         {"x": x}, x + x),
    ]
    col = rng.random((V, N, 3), dtype=np.float32)
    m = (rng.random((V, N, 1)) < 0.9).astype(np.float32)
    cases += [
        ("Mul(c[V,N,3], m[V,N,1])", [helper.make_node("Mul", ["c", "m"], ["y"])], [],
         {"c": col, "m": m}, col * m),
        ("Mul(c, MatMul(m, ones[1,3]))", [helper.make_node("MatMul", ["m", "ones3"], ["m3"]),
                                          helper.make_node("Mul", ["c", "m3"], ["y"])],
         [c(np.ones((1, 3), np.float32), "ones3")], {"c": col, "m": m}, col * m)]
    g = rng.uniform(0, 7, (V * N, 1)).astype(np.float32)
    centres = np.arange(8, dtype=np.float32)
    cases += [
        ("Sub(g[VN,1], centres[8])", [helper.make_node("Sub", ["g", "centres"], ["y"])],
         [c(centres, "centres")], {"g": g}, g - centres),
        ("Gemm(g[VN,1], ones[1,8], -centres)", [helper.make_node("Gemm", ["g", "ones8", "negc"],
                                                                 ["y"])],
         [c(np.ones((1, 8), np.float32), "ones8"), c(-centres, "negc")], {"g": g}, g - centres)]
    p = rng.standard_normal((N, 3)).astype(np.float32)
    freqs = (2.0 ** np.arange(6, dtype=np.float32)) * np.float32(np.pi)
    block = np.zeros((3, 18), np.float32)
    for i in range(3):
        block[i, 6 * i:6 * i + 6] = freqs
    want = (p[:, :, None] * freqs).reshape(N, 18)
    cases += [
        ("Mul(p[N,3,1], freqs[6])", [helper.make_node("Mul", ["p", "freqs"], ["y3"]),
                                     helper.make_node("Reshape", ["y3", "shape18"], ["y"])],
         [c(freqs, "freqs"), c(np.array([N, 18], np.int64), "shape18")],
         {"p": p[:, :, None]}, want),
        ("MatMul(p[N,3], block-diagonal freqs)", [helper.make_node("MatMul", ["p", "block"],
                                                                   ["y"])],
         [c(block, "block")], {"p": p}, want)]
    R, S = max(1, N // 64), 64
    for K, D in ((64, 16), (65, 16), (66, 17)):
        y = rng.standard_normal((R, 1, S, K)).astype(np.float32)
        wgt = rng.standard_normal((4, K, D)).astype(np.float32)
        cases.append((f"MatMul([{R},1,{S},{K}], [4,{K},{D}])",
                      [helper.make_node("MatMul", ["yr", "w"], ["y"])], [c(wgt, "w")],
                      {"yr": y}, y @ wgt))
    # The kernels that are most of the rest: exact GELU three ways, the residual Add + LayerNorm
    # against the contrib SkipLayerNormalization.
    hid = rng.standard_normal((N, 4 * C)).astype(np.float32)
    from math import erf, sqrt
    exact_erf = np.vectorize(erf)(hid.astype(np.float64) / sqrt(2))
    gelu = (0.5 * hid * (1 + exact_erf)).astype(np.float32)
    r2 = c(np.array(2 ** -0.5, np.float32), "r2")
    half = c(np.array(0.5, np.float32), "half")
    one = c(np.array(1.0, np.float32), "one")
    cases += [
        ("Gelu", [helper.make_node("Gelu", ["h"], ["y"])], [], {"h": hid}, gelu),
        ("com.microsoft Gelu", [helper.make_node("Gelu", ["h"], ["y"], domain="com.microsoft")],
         [], {"h": hid}, gelu),
        ("0.5 h (1 + Erf(h / sqrt 2))", [helper.make_node("Mul", ["h", "r2"], ["a"]),
                                         helper.make_node("Erf", ["a"], ["e"]),
                                         helper.make_node("Add", ["e", "one"], ["e1"]),
                                         helper.make_node("Mul", ["h", "half"], ["hh"]),
                                         helper.make_node("Mul", ["hh", "e1"], ["y"])],
         [r2, half, one], {"h": hid}, gelu)]
    a_, b_ = (rng.standard_normal((N, C)).astype(np.float32) for _ in range(2))
    s_ = a_ + b_
    ln = (s_ - s_.mean(-1, keepdims=True)) / np.sqrt(s_.var(-1, keepdims=True) + 1e-5)
    gamma, beta = c(np.ones(C, np.float32), "gamma"), c(np.zeros(C, np.float32), "beta")
    cases += [
        ("Add + LayerNormalization", [helper.make_node("Add", ["a", "b"], ["s"]),
                                      helper.make_node("LayerNormalization", ["s", "gamma", "beta"],
                                                       ["y"], axis=-1, epsilon=1e-5)],
         [gamma, beta], {"a": a_, "b": b_}, ln),
        ("com.microsoft SkipLayerNormalization",
         [helper.make_node("SkipLayerNormalization", ["a", "b", "gamma", "beta"], ["y"],
                           domain="com.microsoft", epsilon=1e-5)],
         [gamma, beta], {"a": a_, "b": b_}, ln)]
    print(f"x [{V}, {N}, {C}] float32, {args.threads} threads, median (min) of {args.runs} calls")
    for name, nodes, inits, feed, want in cases:
        sess = session(nodes, inits, args.threads, tuple(feed))
        got = sess.run(None, feed)[0].reshape(want.shape)
        err = float(np.abs(got - want).max())
        times = []
        for _ in range(args.runs):
            t = time.perf_counter()
            sess.run(None, feed)
            times.append(time.perf_counter() - t)
        print(f"  {name:38s} {statistics.median(times) * 1e3:7.3f} ms ({min(times) * 1e3:.3f})"
              f"   max |error| {err:.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

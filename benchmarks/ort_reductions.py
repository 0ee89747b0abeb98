"""Reductions over the leading (view) axis in ONNX Runtime: ``ReduceSum`` / ``ReduceMax`` against
``MatMul`` with a ones row, on the renderer's shape (the facts behind
``export.fast_renderer._sum_views``).

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


def session(nodes, initializers, threads: int) -> ort.InferenceSession:
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT,
                                                                         None)],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
                              initializer=initializers)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 20)])
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
    graphs = {
        "ReduceSum(axis 0)": ([helper.make_node("ReduceSum", ["x", "axis0"], ["y"], keepdims=0)],
                              [axis0], x.sum(0)),
        "MatMul(ones[1,V], x[V,-1])": ([helper.make_node("Reshape", ["x", "flat"], ["x2"]),
                                        helper.make_node("MatMul", ["ones", "x2"], ["y"])],
                                       [flat, ones], x.sum(0)),
        "ReduceMax(axis 0)": ([helper.make_node("ReduceMax", ["x", "axis0"], ["y"], keepdims=0)],
                              [axis0], x.max(0)),
        "Add(x, x) (one same-shape pass)": ([helper.make_node("Add", ["x", "x"], ["y"])], [],
                                            x + x),
    }
    print(f"x [{V}, {N}, {C}] float32, {args.threads} threads, median (min) of {args.runs} calls")
    for name, (nodes, inits, want) in graphs.items():
        sess = session(nodes, inits, args.threads)
        got = sess.run(None, {"x": x})[0].reshape(want.shape)
        err = float(np.abs(got - want).max())
        times = []
        for _ in range(args.runs):
            t = time.perf_counter()
            sess.run(None, {"x": x})
            times.append(time.perf_counter() - t)
        print(f"  {name:34s} {statistics.median(times) * 1e3:7.3f} ms ({min(times) * 1e3:.3f})"
              f"   max |error| {err:.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

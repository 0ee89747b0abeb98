"""The I/O spec of the two IRIS graphs, as export sees it.

The spec itself (names, dtypes, axes, tolerances, ``IO_SPEC_VERSION``) is declared once, in the
torch-free ``iris_runtime.io_spec``, and re-exported here (the same objects: a change to
``RENDERER["tolerance"]`` is seen by both). This module adds only the exporter's own settings.
"""
from __future__ import annotations

from iris_runtime.io_spec import (ENCODER, EXPLICIT_RGB_AXES, EXPLICIT_RGB_INPUTS, GRAPHS,
                                  IO_SPEC_VERSION, OPTIONAL_GRAPHS, RENDERER, RENDERER_VIEWS,
                                  spec_for)

#: ONNX opset of the graphs unless ``--opset`` says otherwise: 20 has ``Gelu`` and the current
#: ``GridSample``; onnxruntime >= 1.17 runs it.
DEFAULT_OPSET = 20
#: The dynamo exporter silently raises lower opsets to 18, so export refuses them instead.
MIN_OPSET = 18

__all__ = ["IO_SPEC_VERSION", "DEFAULT_OPSET", "MIN_OPSET", "ENCODER", "RENDERER",
           "RENDERER_VIEWS", "EXPLICIT_RGB_INPUTS", "EXPLICIT_RGB_AXES", "GRAPHS", "OPTIONAL_GRAPHS",
           "spec_for"]

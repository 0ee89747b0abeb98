"""The I/O spec of the two IRIS graphs, as export sees it.

The spec itself (names, dtypes, axes, tolerances, ``IO_SPEC_VERSION``) is declared once, in the
torch-free ``iris_runtime.io_spec``, and re-exported here (the same objects: a change to
``RENDERER["tolerance"]`` is seen by both). This module adds only the exporter's own settings.
"""
from __future__ import annotations

from iris_runtime.io_spec import (ENCODER, ENCODER_CAMERAS, EXPLICIT_RGB_AXES, EXPLICIT_RGB_INPUTS,
                                  GRAPHS, IO_SPEC_VERSION, OPTIONAL_GRAPHS, RENDERER,
                                  RENDERER_VIEWS, spec_for)

#: ONNX opset of the graphs unless ``--opset`` says otherwise: 20 has ``Gelu`` and the current
#: ``GridSample``; onnxruntime >= 1.17 runs it.
DEFAULT_OPSET = 20
#: The dynamo exporter silently raises lower opsets to 18, so export refuses them instead.
MIN_OPSET = 18



def base_graph(name: str) -> str:
    """The graph whose I/O spec the exported graph ``name`` has: ``name`` itself for a graph of
    ``GRAPHS`` or ``OPTIONAL_GRAPHS``, else the graph it is a variant of (the int8 renderer,
    "renderer_int8" -> "renderer")."""
    return name if name in GRAPHS or name in OPTIONAL_GRAPHS else "renderer"


__all__ = ["base_graph", "IO_SPEC_VERSION", "DEFAULT_OPSET", "MIN_OPSET", "ENCODER", "RENDERER",
           "RENDERER_VIEWS", "ENCODER_CAMERAS", "EXPLICIT_RGB_INPUTS", "EXPLICIT_RGB_AXES",
           "GRAPHS", "OPTIONAL_GRAPHS", "spec_for"]

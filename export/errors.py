"""Typed errors of ``iris-export``. Each also derives from the built-in exception a caller would
naturally catch (``FileExistsError`` for an existing output, ``ValueError`` for a bad argument),
and every message fits on one line: the CLI prints it as is, without a traceback.

A checkpoint that cannot be read raises ``iris_train.CheckpointError`` (an ``IrisError`` and a
``ValueError``), which export lets through unchanged.
"""
from __future__ import annotations

from iris_runtime.errors import IrisError


class ExportError(IrisError):
    """Base class of every error ``iris-export`` raises on purpose (an ``IrisError``, the project's
    one base class, so ``except IrisError`` catches export failures too)."""


class OutputExistsError(ExportError, FileExistsError):
    """The output directory exists and ``force`` was not given."""


class ExportArgumentError(ExportError, ValueError):
    """An argument of the export is invalid (unsupported opset, unknown quantisation...)."""


class ValidationError(ExportError):
    """ONNX Runtime disagrees with torch beyond the spec's tolerance, or a graph breaks its I/O spec.

    ``graph`` and ``output`` name what failed, ``error`` is the max abs error reached (``inf`` for
    non-finite values or a shape mismatch), ``tolerance`` the spec's bound, ``probe`` the probe input.
    """

    def __init__(self, message: str, *, graph: str, output: str | None = None,
                 error: float | None = None, tolerance: float | None = None,
                 probe: str | None = None):
        super().__init__(message)
        self.graph = graph
        self.output = output
        self.error = error
        self.tolerance = tolerance
        self.probe = probe


__all__ = ["ExportError", "OutputExistsError", "ExportArgumentError", "ValidationError"]

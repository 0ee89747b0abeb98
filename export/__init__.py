"""iris-export: IRIS split into two validated ONNX graphs and a manifest (needs torch + onnx).

    from export import export_model
    export_model("ckpt.pt", "out/", quantize="int8")     # out/encoder.onnx, renderer.onnx, iris.json

Modules: ``io_spec`` (the declarative I/O spec; torch-free), ``graphs`` (export wrappers and ONNX
export), ``validate`` (checker + ONNX Runtime vs torch), ``manifest`` (``iris.json``),
``pipeline`` (``export_model``), ``cli`` (``iris-export``). Attributes are imported lazily so that
``iris-export --help`` and ``export.io_spec`` do not pay for importing torch.
"""
from __future__ import annotations

_LAZY = {
    "export_model": "pipeline", "EncoderGraph": "graphs", "RendererGraph": "graphs",
    "validate": "validate", "ExportError": "errors", "OutputExistsError": "errors",
    "ExportArgumentError": "errors", "ValidationError": "errors",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        import importlib
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

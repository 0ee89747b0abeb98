"""ONNX Runtime's fused ``com.microsoft`` contrib operators as torch custom ops, for the dynamo
exporter (``export.fast_renderer.FastRendererGraph(model, contrib=True)``).

Each op is a ``torch.library`` custom op whose eager implementation is the plain torch math (so the
wrapper runs, and is tested, in torch), plus an onnxscript translation that emits the contrib node
(``CUSTOM_TRANSLATION_TABLE``, passed to ``torch.onnx.export``). The onnxscript tracer needs an ONNX
schema for every op it emits; onnx does not know ONNX Runtime's contrib domain, so the subset of
each schema used here is registered with ``onnx.defs.register_schema`` on first use
(``register_schemas``; a schema onnx already has is left alone).

* ``skip_layer_norm(x, skip, gamma, beta, bias, eps)`` -> ``(LayerNorm(s), s)`` with
  ``s = x + skip + bias``: ``SkipLayerNormalization`` (outputs: output, mean, inv_std_var,
  input_skip_bias_sum; the middle two unused). CPU kernel: 2-D and 3-D inputs.
* ``bias_gelu(x, bias)`` -> ``gelu(x + bias)`` (erf form): ``BiasGelu``.
(``MultiHeadAttention`` was here while validity masks were 0 / 1: its ``key_padding_mask`` cannot
carry fractional weights.)

Both load in ONNX Runtime's CPU provider and match their plain-op forms (tests/test_fast_renderer.py
checks the exported "fast-contrib" renderer within 1e-5 of torch; docs/PERFORMANCE.md, "The fast
renderer graph").
"""
from __future__ import annotations

import onnx
import torch
import torch.nn.functional as F

DOMAIN = "com.microsoft"

# -- torch side ---------------------------------------------------------------------------------


@torch.library.custom_op("iris_fast::skip_layer_norm", mutates_args=())
def skip_layer_norm(x: torch.Tensor, skip: torch.Tensor, gamma: torch.Tensor, beta: torch.Tensor,
                    bias: torch.Tensor, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    s = x + skip + bias
    return F.layer_norm(s, (s.shape[-1],), gamma, beta, eps), s


@skip_layer_norm.register_fake
def _(x, skip, gamma, beta, bias, eps):
    return torch.empty_like(x), torch.empty_like(x)


@torch.library.custom_op("iris_fast::bias_gelu", mutates_args=())
def bias_gelu(x: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    return F.gelu(x + bias)


@bias_gelu.register_fake
def _(x, bias):
    return torch.empty_like(x)


# -- ONNX side ----------------------------------------------------------------------------------
def _schemas() -> list:
    from onnx.defs import OpSchema
    FP, opt = OpSchema.FormalParameter, OpSchema.FormalParameterOption.Optional
    T = [("T", ["tensor(float)"], "float32")]

    def attr(name, kind, required=False):
        return OpSchema.Attribute(name, kind, name, required=required)

    return [
        OpSchema("SkipLayerNormalization", DOMAIN, 1, doc="ONNX Runtime contrib op (subset).",
                 inputs=[FP("input", "T"), FP("skip", "T"), FP("gamma", "T"),
                         FP("beta", "T", param_option=opt), FP("bias", "T", param_option=opt)],
                 outputs=[FP("output", "T"), FP("mean", "U", param_option=opt),
                          FP("inv_std_var", "U", param_option=opt),
                          FP("input_skip_bias_sum", "T", param_option=opt)],
                 type_constraints=T + [("U", ["tensor(float)"], "float32")],
                 attributes=[attr("epsilon", OpSchema.AttrType.FLOAT)]),
        OpSchema("BiasGelu", DOMAIN, 1, doc="ONNX Runtime contrib op.",
                 inputs=[FP("A", "T"), FP("B", "T")], outputs=[FP("C", "T")],
                 type_constraints=T),
    ]


def register_schemas() -> None:
    """Make the contrib ops used here known to onnx (idempotent)."""
    for schema in _schemas():
        try:
            onnx.defs.get_schema(schema.name, schema.since_version, schema.domain)
        except onnx.defs.SchemaError:
            onnx.defs.register_schema(schema)


def translation_table() -> dict:
    """``custom_translation_table`` for ``torch.onnx.export(dynamo=True)``."""
    import onnxscript

    register_schemas()
    ms = onnxscript.values.Opset(DOMAIN, 1)

    def skip_layer_norm_onnx(x, skip, gamma, beta, bias, eps: float):
        out, _mean, _inv_std, total = ms.SkipLayerNormalization(x, skip, gamma, beta, bias,
                                                                epsilon=eps, _num_outputs=4)
        return out, total

    def bias_gelu_onnx(x, bias):
        return ms.BiasGelu(x, bias)

    ops = torch.ops.iris_fast
    return {ops.skip_layer_norm.default: skip_layer_norm_onnx,
            ops.bias_gelu.default: bias_gelu_onnx}


__all__ = ["DOMAIN", "skip_layer_norm", "bias_gelu", "register_schemas", "translation_table"]

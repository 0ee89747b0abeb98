"""Float32 tolerances derived from the format and the size of the computation, not measured.

Why. Two float32 evaluations of one quantity that differ only in rounding -- another order or
blocking of a sum, another SIMD width (AVX2 vs AVX-512 kernels of MKL, oneDNN, OpenBLAS or ONNX
Runtime's MLAS), FMA contraction or not, a sum split over threads, another kernel for another
batch size or row length -- differ by an amount that depends on the CPU and the thread count. A
literal ``1e-6`` that held on one machine is a measurement of that machine: the README's test
command failed on an Intel Xeon at 1.07e-6 against the literal 1e-6 of a comparison written on an
AMD EPYC. A tolerance has to bound every machine's rounding.

The model (used by every float32 tolerance of tests/ that compares two roundings):

* float32 rounds to nearest with unit roundoff ``u = EPS32 / 2 = 2^-24``: each operation errs by
  at most ``u`` relative, i.e. by at most ``u * scale`` when the values it combines are of
  magnitude ``scale``. A computation that accumulates ``n`` rounded terms (a dot product of
  length K is K terms; a chain of layers is the sum of its reductions' lengths) errs by at most
  ``n * u * scale`` (Higham, *Accuracy and Stability of Numerical Algorithms*, 2nd ed., Lemma 3.1,
  gamma_n), and two evaluations of it by at most twice that: ``n * EPS32 * scale``, a strict bound.
* That bound is reached only if every rounding errs fully in the same direction. Rounding errors
  of different operations behave as independent, zero-mean and uniform on
  ``[-ulp/2, ulp/2]`` (standard deviation at most ``u * scale / sqrt(3)``), so n of them add up
  to a standard deviation of ``u * scale * sqrt(n / 3)`` and the difference of two evaluations
  to ``EPS32 * scale * sqrt(n / 6)`` (Higham & Mary, "A new approach to probabilistic rounding
  error analysis", SIAM J. Sci. Comput. 41(5), 2019, make this rigorous up to a constant). We
  allow ``SIGMAS = 6`` standard deviations: ``EPS32 * scale * sqrt(6 n)`` (a Gaussian tail of
  2e-9 per compared entry).
* ``f32_tol(n, scale)`` is the smaller of the two, ``EPS32 * scale * min(n, sqrt(6 n))``: the
  strict bound for short computations (n <= 6), the statistical one beyond.

``scale`` is the magnitude of the values being combined, which for the networks below is taken as
the magnitude of the compared output: their blocks are LayerNorm'd and residual, so an error made
in one layer reaches the output with a gain of order one (an assumption, not a theorem). Checked
on an AMD EPYC with AVX2 kernels and with the SSE ones (``ATEN_CPU_CAPABILITY=default
MKL_ENABLE_INSTRUCTIONS=SSE4_2 ONEDNN_MAX_CPU_ISA=SSE41 OPENBLAS_CORETYPE=Prescott``), at 1 and 2
threads: the largest measured difference was 16% of its network tolerance (the depth rendered
from view-permuted scenes), most were below 5%; the strict short-chain bounds were met at up to 52% (a single
rounding), as they must be. Transcendental functions (exp, log, erf in GELU, sqrt) are counted as a few
terms each: their vectorised implementations are within a few ulp, not half of one.

For the networks the term counts come from the model's config (``ModelConfig.to_dict()`` or an
export's ``iris.json`` ``config``), summed over the chain from the inputs to the compared output:

* one pre-norm attention block of width W, h heads, over T tokens, MLP ratio r:
  LayerNorm (mean and variance, 2W), q/k/v projection (W), scores (W/h), softmax normaliser and
  weighted sum of values (T each), output projection (W), LayerNorm (2W), MLP (W then rW)
  -> ``7W + W/h + 2T + rW`` (``attention_block_terms``);
* the rest is written out in ``encoder_terms`` and ``renderer_terms``.

A tolerance derived this way is much looser than one ulp of the output, so every test that uses it
says in a comment what a real bug would move the quantity by; where the property is exact in
exact arithmetic, a float64 twin of the test holds it to ~1e-10 (the float64 rounding of the same
chain: ``EPS64 * sqrt(6 n)`` is below 1e-12 for every n here).
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

#: float32 machine epsilon, 2^-23 (the spacing of float32 numbers at 1); u = EPS32 / 2.
EPS32 = float(np.finfo(np.float32).eps)
#: float32 unit roundoff, 2^-24.
U32 = EPS32 / 2
#: float64 machine epsilon, 2^-52.
EPS64 = float(np.finfo(np.float64).eps)
#: Standard deviations of the summed rounding errors that a tolerance allows (module docstring).
SIGMAS = 6.0
#: Terms charged to one transcendental function (exp, log, sigmoid, erf, sqrt): vectorised
#: implementations are accurate to a few ulp (oneDNN / MLAS / SLEEF: <= 4 ulp), not 0.5.
TRANSCENDENTAL_TERMS = 8


def f32_tol(n_terms: float, scale: float = 1.0) -> float:
    """How far two float32 evaluations of one quantity of magnitude ``scale``, computed through
    ``n_terms`` accumulated roundings in possibly different orders, may differ:
    ``EPS32 * scale * min(n, sqrt(6 n))`` (module docstring: the strict bound for n <= 6, six
    standard deviations of the summed rounding errors beyond)."""
    n = max(float(n_terms), 1.0)
    return EPS32 * float(scale) * min(n, SIGMAS * math.sqrt(n / 6))


def f64_tol(n_terms: float, scale: float = 1.0) -> float:
    """``f32_tol``'s float64 twin: ``EPS64 * scale * min(n, sqrt(6 n))``."""
    n = max(float(n_terms), 1.0)
    return EPS64 * float(scale) * min(n, SIGMAS * math.sqrt(n / 6))


def _get(config: Any, key: str, default: Any = None) -> Any:
    if isinstance(config, Mapping):
        return config.get(key, default)
    return getattr(config, key, default)


def attention_block_terms(width: int, heads: int, tokens: int, mlp_ratio: float = 4.0) -> int:
    """Accumulated terms through one pre-norm attention block (module docstring):
    ``7W + W/h + 2T + rW`` plus the softmax's exp and the GELU."""
    return (7 * width + width // heads + 2 * tokens + int(mlp_ratio * width)
            + 2 * TRANSCENDENTAL_TERMS)


def correlation_head_terms(config: Any) -> int:
    """The correlation camera head (iris_train/correlation.py) from the images to its pose MLP's
    input, summed over its reductions (its GroupNorms' statistics are the long ones: channels per
    group times positions)."""
    H, W, p = _get(config, "image_height"), _get(config, "image_width"), _get(config, "patch_size")
    s = _get(config, "correlation_scale", 2)
    h, w = H // p, W // p
    h2, w2 = s * h, s * w                       # correlation grid
    c, e, groups = 64, 64, 8                    # CORRELATION_CHANNELS, EVIDENCE_CHANNELS, NORM_GROUPS
    half = (H // 2) * (W // 2)                  # after the stem's first stride-2 conv
    second = half // 4 if s == 2 else half      # after its second conv (stride 2 at scale 2)
    n = 3 * 9 + 2 * (c // 2 // groups) * half   # conv 3x3x3, GroupNorm
    n += 9 * (c // 2) + 2 * (c // groups) * second + 9 * c      # conv, GroupNorm, conv
    n += (p // 8) ** 2                          # average pool (patches above 8)
    n += c + c + TRANSCENDENTAL_TERMS           # L2 normalisation, correlation dot product
    n += h2 * w2 + 2 * (e // groups) * h2 * w2  # 1x1 conv over view 0's positions, GroupNorm
    n += 9 * e + 2 * (e // groups) * h2 * w2    # 3x3 conv, GroupNorm
    n += 9 * e + 2 * (e // groups) * h * w      # 3x3 stride-2 conv, GroupNorm
    n += 3 * h * w + TRANSCENDENTAL_TERMS       # mean, softmax, keypoint
    return n


def encoder_terms(config: Any, views: int, output: str = "cameras") -> int:
    """Accumulated terms from the images to the encoder graph's ``output`` ("field_maps",
    "cameras": world_from_cam (and focal), or "focal" alone, which reads token 0 only and never
    the correlation head's evidence) for ``views`` views in the batch (references and queries:
    the cross-view attention rows are that long)."""
    d = _get(config, "encoder_width")
    heads, r = _get(config, "encoder_heads"), _get(config, "mlp_ratio", 4.0)
    H, W, p = _get(config, "image_height"), _get(config, "image_width"), _get(config, "patch_size")
    tokens = (H // p) * (W // p) + 1            # patches and the camera token
    n = 3 * p * p                               # patch embedding
    n += _get(config, "encoder_pairs") * (attention_block_terms(d, heads, tokens, r)
                                          + attention_block_terms(d, heads, views * tokens, r))
    n += 2 * d                                  # final LayerNorm
    if output == "field_maps":                  # LatentField.prepare: LayerNorm, projection, to_kv
        fw = _get(config, "field_width")
        return n + 2 * d + d + fw
    if output == "focal":                       # focal MLP (GELU), sigmoid, exp
        return n + d + d // 2 + 3 * TRANSCENDENTAL_TERMS
    if output != "cameras":
        raise ValueError(f"output: 'field_maps', 'cameras' or 'focal', got {output!r}")
    # Pose MLP (its input: two tokens, plus the evidence for the correlation head), GELU,
    # 6D -> rotation (two normalisations and a projection), the focal's MLP, sigmoid and exp.
    n_in = 2 * d
    if _get(config, "camera_head", "tokens") == "correlation":
        n += correlation_head_terms(config)
        n_in += 3 * 64
    return n + n_in + d + 3 * (3 + TRANSCENDENTAL_TERMS) + d + d // 2 + 3 * TRANSCENDENTAL_TERMS


def renderer_terms(config: Any, views: int) -> int:
    """Accumulated terms from the renderer graph's inputs (field maps, grid, cues, mask, ...) to
    its rgb and weights (hence depth = sum(weights * z)), for ``views`` views per point: the
    bilinear sample, the latent field (masked max and view transformer over the views), the
    position/direction encodings, the ray transformer over the samples, the pool and the heads."""
    fw, heads = _get(config, "field_width"), _get(config, "field_heads")
    r, S = _get(config, "mlp_ratio", 4.0), _get(config, "samples")
    n = 4 + 4                                   # bilinear sample (4 taps), cue projection (4)
    n += views                                  # masked max over views
    n += _get(config, "view_blocks", 1) * attention_block_terms(fw, heads, views, r)
    enc = 3 * (1 + 2 * _get(config, "pos_freqs")) + 3 * (1 + 2 * _get(config, "dir_freqs"))
    n += _get(config, "ray_blocks") * (enc + TRANSCENDENTAL_TERMS
                                       + attention_block_terms(fw, heads, S, r))
    n += 2 * fw + S                             # final LayerNorm, pool over samples
    n += fw + fw + 2 * TRANSCENDENTAL_TERMS     # rgb head (MLP, GELU, sigmoid)
    if _get(config, "explicit_rgb", False):     # per-sample logit, softmax, blend, logit
        n += fw + 2 * S + 3 * TRANSCENDENTAL_TERMS
    return n + S                                # depth = sum over samples of weight * z


def render_tol(config: Any, views: int, scale: float = 1.0) -> float:
    """Two renders (rgb in [0, 1], depth in [0, far]) whose renderer calls differ only in
    rounding (chunking, culling, workers, windows): ``f32_tol(renderer_terms(...), scale)`` with
    ``scale`` the larger of 1 and far."""
    return f32_tol(renderer_terms(config, views), max(1.0, scale))


def encoder_tol(config: Any, views: int, output: str = "cameras", scale: float = 1.0) -> float:
    """Two encoder evaluations (other batch, other attention-row lengths, another kernel) of an
    output of magnitude ``scale``: ``f32_tol(encoder_terms(...), scale)``."""
    return f32_tol(encoder_terms(config, views, output), scale)

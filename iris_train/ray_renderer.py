"""Ray renderer: compose the point-wise latent features along a target ray (Algorithm 2).

Per block l, each sample's feature is enriched with sinusoidal encodings of its position and of the
ray direction (ψ^(l), additive), then the ray transformer attends over the S samples. A final norm,
a mean pool over samples and a bounded rgb head give the colour. The per-sample weights of the last
ray attention, averaged over heads and query samples, form a distribution over samples (they sum to
one) that gives the soft depth D = Σ w_m z_m.

Each sample has a weight s in [0, 1], its best view's validity (``geometry.validity``: 1 for a
sample seen in some reference image, fading to 0 just outside the images). Samples of weight 0
project validly into no reference view and carry no information: they are masked out of the ray
attention (as keys), of the pool and of the depth weights. The renderer is therefore exactly
invariant to dropping them (and to the order of samples: there is no sample-index embedding,
position enters only through γ_pos(x)), which the runtime uses to skip them. A ray with no valid
sample gets rgb = head(0) and all-zero weights. A fractional weight enters the attention through
``layers.validity_bias`` and the pool and the colour blend linearly, so a sample leaving the
views leaves the render continuously.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

# The blend is clamped to [BLEND_EPS, 1 - BLEND_EPS] before its logit (one value for the
# trainer and the runtime, which recomposes the colour at two scales).
from iris_runtime.colour import BLEND_EPS

from .config import ModelConfig
from .layers import MLP, masked_softmax, sinusoidal_encoding, validity_bias



class RayBlock(nn.Module):
    """Pre-norm masked self-attention over the samples of a ray, then an MLP."""

    def __init__(self, width: int, heads: int, mlp_ratio: float):
        super().__init__()
        self.heads = heads
        self.norm1 = nn.LayerNorm(width)
        self.qkv = nn.Linear(width, 3 * width)
        self.proj = nn.Linear(width, width)
        self.norm2 = nn.LayerNorm(width)
        self.mlp = MLP(width, int(width * mlp_ratio), width)

    def forward(self, x: torch.Tensor, sample_mask: torch.Tensor, need_weights: bool = True):
        """``x [R, S, W]``, sample weights ``sample_mask [R, S]`` -> ``x [R, S, W]``, attention
        ``[R, H, S, S]``.

        Without ``need_weights`` the fused SDPA kernel runs with an additive finite mask: on every
        query row with at least one valid key it is the same softmax (exp(-1e30) is exactly 0);
        rows with no valid key differ, but they belong to rays with no valid sample, whose
        outputs are pooled away. Returns ``None`` for the attention then.
        """
        R, S, W = x.shape
        H = self.heads
        q, k, v = self.qkv(self.norm1(x)).reshape(R, S, 3, H, W // H).permute(2, 0, 3, 1, 4)
        if need_weights:
            logits = (q @ k.transpose(-1, -2)) * (W // H) ** -0.5             # [R, H, S, S]
            attn = masked_softmax(logits, sample_mask[:, None, None, :], dim=-1)
            out = attn @ v
        else:
            bias = validity_bias(sample_mask.to(x.dtype))[:, None, None, :]
            out, attn = F.scaled_dot_product_attention(q, k, v, attn_mask=bias), None
        out = out.transpose(1, 2).reshape(R, S, W)
        x = x + self.proj(out)
        return x + self.mlp(self.norm2(x)), attn


class RayTransformer(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        pos_dim = 3 * (1 + 2 * cfg.pos_freqs)
        dir_dim = 3 * (1 + 2 * cfg.dir_freqs)
        self.pos_freqs, self.dir_freqs = cfg.pos_freqs, cfg.dir_freqs
        self.inject = nn.ModuleList(nn.Linear(pos_dim + dir_dim, cfg.field_width)   # ψ^(l)
                                    for _ in range(cfg.ray_blocks))
        self.blocks = nn.ModuleList(RayBlock(cfg.field_width, cfg.field_heads, cfg.mlp_ratio)
                                    for _ in range(cfg.ray_blocks))

    def forward(self, f: torch.Tensor, positions: torch.Tensor, directions: torch.Tensor,
                sample_mask: torch.Tensor, need_weights: bool = True):
        """``f [R, S, W]``, ``positions [R, S, 3]``, ``directions [R, 3]``, sample weights
        ``sample_mask [R, S]``."""
        R, S, _ = f.shape
        unit_dir = directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        e_pos = sinusoidal_encoding(positions, self.pos_freqs)                       # [R, S, P]
        e_dir = sinusoidal_encoding(unit_dir, self.dir_freqs)[:, None].expand(R, S, -1)
        enc = torch.cat([e_pos, e_dir], dim=-1)
        attn = None
        last = len(self.blocks) - 1
        for i, (inject, block) in enumerate(zip(self.inject, self.blocks)):
            # Only the last block's weights are read (soft depth), so the others take the fused path.
            f, attn = block(f + inject(enc), sample_mask, need_weights=need_weights and i == last)
        return f, attn


class RayRenderer(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.ray_transformer = RayTransformer(cfg)
        self.norm = nn.LayerNorm(cfg.field_width)
        self.rgb_head = MLP(cfg.field_width, cfg.field_width, 3)
        self.explicit_rgb = cfg.explicit_rgb
        if cfg.explicit_rgb:
            # Per-sample logit of the colour blend (and of the soft depth); the residual head
            # starts at zero, so a new model renders the blend itself.
            self.sample_logit = nn.Linear(cfg.field_width, 1)
            nn.init.zeros_(self.rgb_head[-1].weight)
            nn.init.zeros_(self.rgb_head[-1].bias)

    def forward(self, f: torch.Tensor, positions: torch.Tensor, directions: torch.Tensor,
                sample_mask: torch.Tensor, need_weights: bool = True,
                colours: torch.Tensor | None = None):
        """-> ``rgb [R, 3]`` in (0, 1), per-sample ``weights [R, S]`` (sum 1, or 0 for empty rays).

        With ``explicit_rgb``, ``colours [R, S, 3]`` is the mean reference colour of each sample
        over the views that see it; ``rgb = sigmoid(logit(blend) + head(h))`` with
        ``blend = sum_s w_s colours_s`` and ``w = masked softmax of the per-sample logits`` times
        the ray's largest sample weight (1 for a ray that sees anything; a ray whose last samples
        leave the views fades to the empty blend), and
        ``weights`` is ``w`` (always returned: it costs nothing). Otherwise ``need_weights=False``
        (training) skips the explicit attention matrix and weights are None.
        """
        if self.explicit_rgb:
            need_weights = False                        # the depth weights are the blend's
        f, attn = self.ray_transformer(f, positions, directions, sample_mask, need_weights)
        m = sample_mask.to(f.dtype)                                                  # [R, S]
        n_valid = m.sum(-1, keepdim=True)                            # [R, 1] (weights: a sum)
        normed = self.norm(f)
        h = (normed * m[..., None]).sum(1) / n_valid.clamp_min(1.0)                  # [R, W]
        if self.explicit_rgb:
            w = (masked_softmax(self.sample_logit(normed)[..., 0], m)
                 * m.amax(-1, keepdim=True))                                          # [R, S]
            blend = (w[..., None] * colours).sum(1).clamp(BLEND_EPS, 1 - BLEND_EPS)  # [R, 3]
            rgb = torch.sigmoid(torch.log(blend) - torch.log1p(-blend) + self.rgb_head(h))
            return rgb, w
        rgb = torch.sigmoid(self.rgb_head(h))
        if attn is None:
            return rgb, None
        # Mean over heads and over valid query samples of the last attention: a distribution
        # over key samples (rows of the softmax sum to one on valid keys).
        per_query = attn.mean(1)                                                     # [R, S, S]
        weights = (per_query * m[..., None]).sum(1) / n_valid.clamp_min(1.0)         # [R, S]
        return rgb, weights

"""Probe inputs of the exported graphs and their torch reference outputs, all seeded
(``export.validate`` runs them through ONNX Runtime and compares):

* encoder, all references: uniform random images and a *scene* (crops of one smooth random
  texture, panned across the views: structured, correlated images), for V in {1, 3, 8},
  ``is_reference`` all True; the reference is ``IrisModel.encode``.
* encoder, with queries: crops of one panned texture split into V references followed by Q
  queries, (V, Q) in ``QUERY_COUNTS``; the reference is ``IrisModel.encode`` of the references
  alone (their rows) and ``IrisModel.locate`` (the queries' poses), so the error covers parity
  and isolation at once. Plus one probe with the queries interleaved among the references
  (``is_reference = [T, F, T, T, F]``) against ``IrisModel.encode_batch``.
* renderer, random: random field maps, grid (partly outside the image), unit cues and random
  validity weights (0, fractional and 1) in which the first sample of every ray is masked in
  every view and (R > 1) the last ray has every sample masked; V' in {1, 3, 8}, R in {1, n}
  and an odd S; the reference is ``RendererGraph`` in torch.
* renderer, scene: the scene encoded by torch, rays through random pixels of a novel pose near
  the last view (plus rays pointing backwards, whose samples lie behind the cameras), inputs
  built by ``Scene.project_samples`` (the torch twin of the runtime's numpy geometry, and
  ``render_rays``' own projection step); the reference is
  ``IrisModel.render_rays`` itself, so these probes also check that the wrapper computes what
  the model computes.
* explicit-colour models (``ModelConfig.explicit_rgb``): the same probes with the renderer's
  ``colours`` input: uniform random RGB in [0, 1] (for R > 2 the first ray black, the second
  white: the blend's clamp at 0 and 1) on the random probes, the scene photos sampled at the
  samples' projections (``IrisModel.field_at``'s rule) on the scene probes.

The builders of single inputs (``scene_images``, ``renderer_inputs``, ``random_renderer_inputs``,
``selected_view_inputs``, ``scene_rays``) serve the tests and the benchmarks too.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from iris_runtime.point_views import select_point_views
from iris_train import geometry as G
from iris_train.model import IrisModel, Scene

from .graphs import RendererGraph, fixed_dims

PROBE_SEED = 0
VIEW_COUNTS = (1, 3, 8)
#: (references, queries) of the encoder probes with queries.
QUERY_COUNTS = ((1, 1), (3, 2), (5, 3))


@dataclass
class Probe:
    """One probe input of a graph, its torch reference outputs and a description for the report."""
    name: str
    inputs: dict[str, torch.Tensor]
    reference: dict[str, np.ndarray]
    info: dict = field(default_factory=dict)


# -- probe inputs -------------------------------------------------------------------------------
def scene_images(n_views: int, height: int, width: int, generator: torch.Generator) -> torch.Tensor:
    """``[V, 3, H, W]`` in [0, 1]: crops of one smooth random texture, panned across the views."""
    canvas_h, canvas_w = height + height // 4, 2 * width
    coarse = F.interpolate(torch.rand(1, 3, 5, 8, generator=generator), size=(canvas_h, canvas_w),
                           mode="bicubic", align_corners=False)
    fine = F.interpolate(torch.rand(1, 3, 12, 20, generator=generator), size=(canvas_h, canvas_w),
                         mode="bicubic", align_corners=False)
    canvas = (0.75 * coarse + 0.25 * fine).clamp(0.0, 1.0)[0]
    xs = np.linspace(0, canvas_w - width, n_views).round().astype(int)
    ys = [(i % 2) * (height // 8) for i in range(n_views)]
    return torch.stack([canvas[:, y:y + height, x:x + width] for x, y in zip(xs, ys)])


def renderer_inputs(scene: Scene, origins: torch.Tensor, directions: torch.Tensor,
                    depths: torch.Tensor) -> dict[str, torch.Tensor]:
    """The renderer graph's inputs for rays ``origins, directions [R, 3]`` at depths ``[R, S]``:
    ``Scene.project_samples`` (the projection step of ``IrisModel.render_rays``, the torch twin of
    the runtime's numpy geometry) under the graph's input names; ``colours`` when the scene
    carries its photos (explicit colour)."""
    s = scene.project_samples(origins, directions, depths)
    inputs = {"field_maps": s.field_maps, "grid": s.grid, "cues": s.cues, "mask": s.mask,
              "positions": s.positions, "directions": s.directions}
    if s.colours is not None:
        inputs["colours"] = s.colours
    return inputs


def random_renderer_inputs(model: IrisModel, n_views: int, n_rays: int, n_samples: int,
                           generator: torch.Generator) -> dict[str, torch.Tensor]:
    """Random renderer inputs with the edge cases in the mask (see the module docstring)."""
    g = generator
    dims = fixed_dims(model.cfg)
    V, R, S = n_views, n_rays, n_samples
    unit = torch.randn(V, R, S, 3, generator=g)
    unit = unit / unit.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    u = torch.rand(V, R, S, generator=g)
    # Validity weights: 0 (35 %), fractional (a sample at an image edge, 20 %) and 1.
    mask = torch.where(u < 0.35, 0.0, torch.where(u < 0.55, (u - 0.35) * 5.0, 1.0))
    mask[:, :, 0] = 0.0                   # a point masked in every view, on every ray
    if R > 1:
        mask[:, -1] = 0.0                 # a ray with every sample masked
    inputs = {
        "field_maps": torch.randn(V, dims["C'"], dims["h"], dims["w"], generator=g),
        "grid": torch.rand(V, R, S, 2, generator=g) * 2.6 - 1.3,
        "cues": torch.cat([unit, torch.rand(V, R, S, 1, generator=g) * 2 - 1], dim=-1),
        "mask": mask,
        "positions": torch.randn(R, S, 3, generator=g) * 0.5,
        "directions": torch.randn(R, 3, generator=g),
    }
    if model.cfg.explicit_rgb:            # reference RGB in [0, 1]; a black and a white ray
        colours = torch.rand(V, R, S, 3, generator=g)
        if R > 2:
            colours[:, 0], colours[:, 1] = 0.0, 1.0
        inputs["colours"] = colours
    return inputs


def selected_view_inputs(inputs: dict[str, torch.Tensor], k: int, generator: torch.Generator
                         ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Per-point pre-selected views (``io_spec.RENDERER_VIEWS``) from view-major renderer
    ``inputs``: each point keeps at most ``k`` of its valid views, drawn at random. Returns
    ``(selected, masked)``: the selected-views inputs (``point_views.select_point_views``, the
    runtime's own builder) and ``inputs`` with the views not kept masked out, which the renderer
    must render to the same values."""
    V, R, S = inputs["mask"].shape
    order = torch.rand(V, R, S, generator=generator).argsort(0)[:k]                # [k, R, S]
    chosen = torch.zeros(V, R, S, dtype=torch.bool).scatter_(0, order, True)
    masked = {**inputs, "mask": inputs["mask"] * chosen}
    selected = select_point_views({n: x.detach().numpy() for n, x in masked.items()})
    return {n: torch.from_numpy(x) for n, x in selected.items()}, masked


def _novel_pose(scene: Scene) -> torch.Tensor:
    """A target pose near the scene's last view: 3 degrees about y, a small translation."""
    a = math.radians(3.0)
    delta = torch.tensor([[math.cos(a), 0.0, math.sin(a), 0.02],
                          [0.0, 1.0, 0.0, -0.01],
                          [-math.sin(a), 0.0, math.cos(a), 0.01],
                          [0.0, 0.0, 0.0, 1.0]], dtype=scene.world_from_cam.dtype)
    return scene.world_from_cam[-1] @ delta


def scene_rays(model: IrisModel, scene: Scene, n_rays: int, generator: torch.Generator):
    """``origins, directions [R, 3]``, bin-centre ``depths [R, S]`` through random pixels of a novel
    pose; for R >= 8 the last R // 8 rays point backwards (behind the reference cameras)."""
    cfg = model.cfg
    H, W = scene.image_size
    uv = G.pixel_centres(H, W)[torch.randperm(H * W, generator=generator)[:n_rays]]
    origins, directions = G.rays_from_pixels(uv, scene.intrinsics(), _novel_pose(scene))
    n_back = n_rays // 8
    if n_back:
        directions = torch.cat([directions[:-n_back], -directions[-n_back:]])
    depths = G.sample_depths(cfg.near, cfg.far, cfg.samples, n_rays, dtype=directions.dtype)
    return origins.contiguous(), directions.contiguous(), depths


def to_numpy(x: torch.Tensor) -> np.ndarray:
    """A contiguous numpy copy of ``x`` (ONNX Runtime's feed)."""
    return np.ascontiguousarray(x.detach().cpu().numpy())


def _mask_info(mask: torch.Tensor) -> dict:
    """Shape and edge-case counts of a view-major mask ``[V, R, S]``."""
    V, R, S = mask.shape
    any_view = (mask > 0).any(0)
    return {"V": V, "R": R, "S": S, "points_masked_in_every_view": int((~any_view).sum()),
            "rays_with_every_sample_masked": int((~any_view.any(-1)).sum())}


def _encoder_reference(maps: torch.Tensor, world_from_cam: torch.Tensor, focal: torch.Tensor) -> dict:
    return {"field_maps": to_numpy(maps), "world_from_cam": to_numpy(world_from_cam),
            "focal": to_numpy(focal)}


@torch.no_grad()
def encoder_probes(model: IrisModel, view_counts=VIEW_COUNTS, query_counts=QUERY_COUNTS,
                   seed: int = PROBE_SEED) -> list[Probe]:
    """All-reference probes, probes with queries after the references, one interleaved probe
    (see the module docstring). ``info``: V (views fed), queries, and for references-first probes
    with queries ``references`` (the isolation check of ``isolation_errors`` uses it)."""
    g = torch.Generator().manual_seed(seed)
    H, W = model.cfg.image_height, model.cfg.image_width
    probes = []
    for V in view_counts:
        for kind, images in (("random", torch.rand(V, 3, H, W, generator=g)),
                             ("scene", scene_images(V, H, W, g))):
            scene = model.encode(images)
            probes.append(Probe(f"{kind} V={V}", {"images": images,
                                                  "is_reference": torch.ones(V, dtype=torch.bool)},
                                _encoder_reference(scene.field_maps, scene.world_from_cam, scene.focal),
                                {"V": V, "queries": 0}))
    for V, Q in query_counts:
        views = scene_images(V + Q, H, W, g)
        # Queries are odd views of the pan (between references), fed after the references.
        queries = [i for i in range(1, V + Q, 2)][:Q]
        queries += [i for i in range(V + Q - 1, 0, -1) if i not in queries][:Q - len(queries)]
        images = views[[i for i in range(V + Q) if i not in queries] + queries]
        is_reference = torch.arange(V + Q) < V
        scene = model.encode(images[:V])
        features, _, _ = model.encode_batch(images[None], is_reference)
        maps = torch.cat([scene.field_maps, model.field.prepare(features[0, V:])])
        poses = torch.cat([scene.world_from_cam, model.locate(images[:V], images[V:])])
        probes.append(Probe(f"scene V={V} + Q={Q} queries", {"images": images,
                                                              "is_reference": is_reference},
                            _encoder_reference(maps, poses, scene.focal),
                            {"V": V + Q, "queries": Q, "references": V}))
    images = scene_images(5, H, W, g)
    is_reference = torch.tensor([True, False, True, True, False])
    features, poses, focal = model.encode_batch(images[None], is_reference)
    probes.append(Probe("scene V=5 interleaved queries", {"images": images, "is_reference": is_reference},
                        _encoder_reference(model.field.prepare(features[0]), poses[0], focal[0]),
                        {"V": 5, "queries": 2}))
    return probes


@torch.no_grad()
def renderer_probes(model: IrisModel, view_counts=VIEW_COUNTS, n_rays: int = 128,
                    seed: int = PROBE_SEED) -> list[Probe]:
    cfg = model.cfg
    g = torch.Generator().manual_seed(seed)
    wrapper = RendererGraph(model).eval()
    probes = []

    def add(name, inputs, reference):
        probes.append(Probe(name, inputs, {"rgb": to_numpy(reference[0]),
                                           "weights": to_numpy(reference[1])},
                            _mask_info(inputs["mask"])))

    odd_samples = max(3, cfg.samples // 4 + 1)
    for V in view_counts:
        shapes = [(1, cfg.samples), (n_rays, cfg.samples), (max(2, n_rays // 4), odd_samples)]
        for R, S in shapes:
            inputs = random_renderer_inputs(model, V, R, S, g)
            add(f"random V'={V} R={R} S={S}", inputs, wrapper(**inputs))
        scene = model.encode(scene_images(V, cfg.image_height, cfg.image_width, g))
        for R in (1, n_rays):
            origins, directions, depths = scene_rays(model, scene, R, g)
            add(f"scene V'={V} R={R} S={cfg.samples}", renderer_inputs(scene, origins, directions, depths),
                model.render_rays(scene, origins, directions, depths, need_weights=True))
    return probes


def renderer_views_probes(model: IrisModel, view_counts=VIEW_COUNTS, n_rays: int = 128,
                          seed: int = PROBE_SEED) -> list[Probe]:
    """Probes of the selected-views renderer (``io_spec.RENDERER_VIEWS``): random and scene
    inputs as in ``renderer_probes``, each point keeping about half of its views
    (``selected_view_inputs``); the reference is the torch model on the same inputs with the
    unselected views masked."""
    cfg = model.cfg
    g = torch.Generator().manual_seed(seed + 1)
    wrapper = RendererGraph(model).eval()
    probes = []

    def add(name, inputs, k):
        selected, masked = selected_view_inputs(inputs, k, g)
        reference = wrapper(**masked)
        probes.append(Probe(f"{name} k={k}", selected, {"rgb": to_numpy(reference[0]),
                                                       "weights": to_numpy(reference[1])},
                            _mask_info(selected["mask"])))

    for V in view_counts:
        k = max(1, (V + 1) // 2)
        for R, S in [(1, cfg.samples), (n_rays, cfg.samples)]:
            add(f"random V={V} R={R} S={S}", random_renderer_inputs(model, V, R, S, g), k)
        scene = model.encode(scene_images(V, cfg.image_height, cfg.image_width, g))
        origins, directions, depths = scene_rays(model, scene, n_rays, g)
        add(f"scene V={V} R={n_rays} S={cfg.samples}",
            renderer_inputs(scene, origins, directions, depths), k)
    return probes


__all__ = ["Probe", "PROBE_SEED", "VIEW_COUNTS", "QUERY_COUNTS", "scene_images", "renderer_inputs",
           "random_renderer_inputs", "selected_view_inputs", "scene_rays", "encoder_probes",
           "renderer_probes", "renderer_views_probes", "to_numpy"]

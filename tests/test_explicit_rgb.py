"""The explicit-colour renderer (``ModelConfig.explicit_rgb``): the colour is a learned blend of
reference RGB sampled at the ray samples plus a bounded residual, and the blend weights are the
soft-depth weights."""
from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from iris_train import build_model, preset  # noqa: E402
from iris_train import geometry as G  # noqa: E402
from iris_train.ray_renderer import BLEND_EPS  # noqa: E402


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return build_model(preset("tiny-rgb")).double().eval()


def _rays(scene, n=64):
    H, W = scene.image_size
    uv = G.pixel_centres(H, W, dtype=torch.float64)[torch.arange(0, H * W, H * W // n)]
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 3] = torch.tensor([0.05, -0.02, 0.01])
    o, d = G.rays_from_pixels(uv, scene.intrinsics(), pose)
    return o, d, G.sample_depths(0.1, 1.0, 64, o.shape[0], dtype=torch.float64)


def test_new_model_renders_its_blend_and_weights_are_a_distribution(model):
    torch.manual_seed(1)
    images = torch.rand(3, 3, 64, 64, dtype=torch.float64)
    scene = model.encode(images)
    o, d, z = _rays(scene)
    with torch.no_grad():
        f, points, mask, colours = model.field_at(scene, o, d, z)
        rgb, w = model.renderer(f, points, d, mask.amax(-1), colours=colours)
    blend = (w[..., None] * colours).sum(1).clamp(BLEND_EPS, 1 - BLEND_EPS)
    torch.testing.assert_close(rgb, blend, rtol=0, atol=1e-12)        # residual head starts at 0
    # Weights: a distribution on rays with a fully valid sample, else the ray's best sample
    # weight in total (rays seen only at an image edge fade out).
    best = mask.amax(-1).amax(-1)
    assert bool((best == 1).sum() > 0)
    torch.testing.assert_close(w.sum(-1), best)
    assert bool((w[mask.amax(-1) == 0] == 0).all())                    # unseen samples: no weight
    # colours are the validity-weighted mean over the views that see the sample of bilinear
    # full-resolution RGB
    uv, z, _ = G.project_points(points, scene.intrinsics(), G.invert_pose(scene.world_from_cam), 64, 64)
    ref = G.sample_bilinear(images, G.pixels_to_grid(uv, 64, 64))
    m = G.validity(uv, z, 64, 64)[..., None]
    torch.testing.assert_close(colours, (ref * m).sum(0) / m.sum(0).clamp_min(1), rtol=0, atol=1e-12)


def test_render_follows_the_reference_pixels(model):
    """Changing a reference photo changes the render (through the sampled RGB, not only through
    the patch features) and a uniform grey scene renders grey: every ray, here those of a
    16 x 16 render (the model's aspect, rays spread over the whole frame; a float64 64 x 64
    render costs ~25 s of one core)."""
    grey = torch.full((3, 3, 64, 64), 0.3, dtype=torch.float64)
    scene = model.encode(grey)
    rgb, _ = model.render(scene, scene.world_from_cam[:1], 16, 16)
    assert rgb.shape == (1, 16, 16, 3)
    torch.testing.assert_close(rgb, torch.full_like(rgb, 0.3), rtol=0, atol=1e-9)


def test_scene_without_images_is_a_typed_error(model):
    import dataclasses
    scene = dataclasses.replace(model.encode(torch.rand(2, 3, 64, 64, dtype=torch.float64)), images=None)
    with pytest.raises(ValueError, match="scene.images"):
        model.render(scene, torch.eye(4, dtype=torch.float64)[None])


def test_subset_keeps_the_matching_photos(model):
    images = torch.rand(4, 3, 64, 64, dtype=torch.float64)
    sub = model.encode(images).subset([0, 2])
    torch.testing.assert_close(sub.images, images[[0, 2]])


def test_blend_views_is_the_runtime_formula():
    """The torch blend of the views (``iris_train.model.blend_views``, here in float64) and the
    runtime's float32 one (``iris_runtime.colour.mean_colour``) agree on the same float32 inputs,
    plain and by angle, to the float32 rounding of a few operations on values in [0, 1] (a wrong
    weighting moves colours by > 1e-2)."""
    import numpy as np

    from iris_runtime.colour import mean_colour
    from iris_train.model import blend_views
    rng = np.random.default_rng(5)
    colours = rng.uniform(0, 1, (5, 7, 9, 3)).astype(np.float32)
    mask = rng.choice([0.0, 0.25, 1.0], (5, 7, 9)).astype(np.float32)
    cos = rng.uniform(-1, 1, (5, 7, 9)).astype(np.float32)
    eps32 = float(np.finfo(np.float32).eps)
    for angle in (0.0, 0.05, 0.005):
        got = blend_views(*(torch.from_numpy(x).double() for x in (colours, mask, cos)),
                          angle).numpy()
        # exp's argument (cos - best) / angle carries the float32 rounding of cos - best (at most
        # eps of |cos - best| <= 2) divided by angle: a relative error of the weights of
        # 2 eps / angle (2e-4 at 0.005), plus a few roundings of the blend.
        tol = 4 * eps32 * (2.0 / angle if angle else 0.0) + 16 * eps32
        np.testing.assert_allclose(got, mean_colour(colours, mask, cos, angle), rtol=0, atol=tol)


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf"), "0.1"])
def test_blend_angle_is_checked(bad):
    import dataclasses

    from iris_runtime.errors import InputError
    with pytest.raises(InputError, match="blend_angle"):
        dataclasses.replace(preset("tiny-rgb"), blend_angle=bad)
    with pytest.raises(InputError, match="blend_angle.*explicit_rgb"):
        dataclasses.replace(preset("tiny"), blend_angle=0.01)

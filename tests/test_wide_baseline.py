"""benchmarks/wide_baseline.py: the angle of a hand-built geometry, the depth error against the
true depth itself, and one tiny scene rendered at its true cameras (weights, the eval's numbers,
the bins partitioning the rays)."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from benchmarks import wide_baseline as WB  # noqa: E402
from iris_runtime import geometry as NG  # noqa: E402

from .conftest import random_model  # noqa: E402
from .np_scenes import look_at  # noqa: E402
from .test_evaluate import plane_scene  # noqa: E402

SIZE = 16


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def on_circle(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([np.cos(a), np.sin(a), 0.0])


def test_surface_angle_of_cameras_around_a_point():
    K = np.array([[SIZE, 0, SIZE / 2], [0, SIZE, SIZE / 2], [0, 0, 1.0]])
    target = on_circle(0.0)
    at_90 = look_at(on_circle(90.0), np.zeros(3))
    at_45 = look_at(on_circle(45.0), np.zeros(3))
    away_20 = look_at(on_circle(20.0), 2 * on_circle(20.0))       # nearer, but looks away
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 50.0]])        # the second: in no frustum
    angle = WB.surface_angles(points, target, np.stack([at_90, away_20]), np.stack([K, K]),
                              SIZE, SIZE)
    assert angle[0] == pytest.approx(90.0, abs=1e-9) and np.isnan(angle[1])
    angle = WB.surface_angles(points, target, np.stack([at_90, away_20, at_45]),
                              np.stack([K, K, K]), SIZE, SIZE)
    assert angle[0] == pytest.approx(45.0, abs=1e-9)
    bins = WB.bin_index(np.array([0.0, 10.0, 10.5, 45.0, 90.0, 91.0, np.nan, np.nan]),
                        np.array([True] * 7 + [False]))
    assert [WB.BIN_NAMES[b] for b in bins] == ["0-10", "0-10", "10-20", "30-45", "45-90", ">90",
                                               "unseen", "no depth"]


def test_ray_stats_of_the_true_depth():
    rng = np.random.default_rng(0)
    S, near, far = 8, 0.1, 1.0
    z = np.broadcast_to(np.linspace(near, far, S + 1)[:-1] + (far - near) / (2 * S), (4, S))
    true = np.array([z[0, 3], 0.5, 0.0, 1.4])
    weights = np.stack([np.eye(S)[3], np.full(S, 1.0 / S), rng.dirichlet(np.ones(S)),
                        0.5 * rng.dirichlet(np.ones(S))])
    stats = WB.ray_stats(weights, z, true, true, near, far)
    np.testing.assert_array_equal(stats["depth_err"][[0, 1, 3]], 0.0)
    assert np.isnan(stats["depth_err"][2]) and np.isnan(stats["mass_near"][2])
    assert stats["max_weight"][0] == 1.0 and stats["entropy"][0] == 0.0
    assert stats["mass_near"][0] == 1.0
    assert stats["entropy"][1] == pytest.approx(1.0) and stats["max_weight"][1] == 1.0 / S
    assert stats["outside"].tolist() == [False, False, False, True]


def test_a_tiny_scene_at_its_true_cameras():
    from iris_train.evaluate import TorchBackend, evaluate, prepare_scene, split_frames
    from iris_train.evaluate.cameras import pose_scene
    model = random_model("tiny-rgb", image_height=SIZE, image_width=SIZE, samples=8)
    scene = plane_scene(size=2 * SIZE)                      # 32 x 32 photos, fitted to 16 x 16
    refs, targets = split_frames(8)
    backend = TorchBackend(model)
    prepared = prepare_scene(scene, 8, (SIZE, SIZE))
    posed = pose_scene(backend, prepared, refs, targets, "true", "true")
    rgb, weights, z, soft = WB.render_target(model, posed.encoded, posed.world_from_cam[1])
    assert weights.shape == z.shape == (SIZE * SIZE, 8)
    assert weights.min() >= 0.0 and weights.sum(-1).max() <= 1.0 + 1e-5
    # The rays of IrisModel.render (one chunk at this size): the same colours and soft depth.
    want_rgb, want_depth = backend.render(posed.encoded, posed.world_from_cam[[1]])
    np.testing.assert_array_equal(rgb, want_rgb.reshape(-1, 3))
    np.testing.assert_array_equal(soft, want_depth.reshape(-1))

    rays, record = WB.scene_rays(model, scene)
    rows = WB.summarise(rays)
    n = len(WB.BIN_NAMES)
    assert [r["bin"] for r in rows] == [*WB.BIN_NAMES, "all", "par<0.25", "par0.25-1", "par>=1"]
    assert sum(r["rays"] for r in rows[:n]) == rows[n]["rays"] == len(targets) * SIZE * SIZE
    # The parallax bins partition the rays whose band some reference sees.
    assert sum(r["rays"] for r in rows[n + 1:]) == np.isfinite(rays["parallax"]).sum() > 0
    assert rows[WB.BIN_NAMES.index("no depth")]["rays"] == 0          # the plane fills every view
    assert np.all(rays["angle"][np.isfinite(rays["angle"])] < 10.0)    # cameras a few degrees apart
    # PSNR and depth Spearman as iris-eval computes them with the true cameras (Seq order).
    seq = evaluate(model, [scene], progress=False, cameras="true")["seq"]["scenes"][0]["model"]
    assert record["psnr"] == seq["psnr"] and record["depth_spearman"] == seq["depth_spearman"]


def test_band_parallax_of_a_sideways_camera():
    """A reference moved by b along x, both looking down +z: the band [0.95 d, 1.05 d] of a ray
    along the optical axis spans f b (1 / 0.95 d - 1 / 1.05 d) pixels in it."""
    f, b, d = 20.0, 0.1, 2.0
    K = np.array([[f, 0, SIZE / 2], [0, f, SIZE / 2], [0, 0, 1.0]])
    ref = np.eye(4)
    ref[0, 3] = b
    origins, directions = np.zeros((2, 3)), np.array([[0.0, 0.0, 1.0]] * 2)
    par = WB.band_parallax(origins, directions, np.array([d, 0.0]), ref[None], K[None], SIZE, SIZE)
    band = WB.NEAR_BAND
    assert par[0] == pytest.approx(f * b * (1 / ((1 - band) * d) - 1 / ((1 + band) * d)), rel=1e-12)
    assert np.isnan(par[1])                                              # no true depth
    behind = WB.band_parallax(origins, -directions, np.array([d, d]), ref[None], K[None], SIZE, SIZE)
    assert np.isnan(behind).all()                                        # seen by no reference


def textured_plane(size: int = 64, depth: float = 0.6, xs=(-0.2, -0.1, 0.0, 0.1, 0.2, 0.05)):
    """Photos of a fronto-parallel textured plane (z = ``depth``) from cameras looking down +z at
    x = ``xs``: (``images [N, 3, size, size]`` in [0, 1], ``world_from_cam [N, 4, 4]``, ``K``)."""
    import cv2
    K = np.array([[1.2 * size, 0, size / 2], [0, 1.2 * size, size / 2], [0, 0, 1.0]])
    # Texels of about 4 pixels, so that bilinear sampling of the photos is faithful.
    texture = cv2.resize(np.random.default_rng(0).uniform(0, 1, (64, 64, 3)).astype(np.float32),
                         (256, 256), interpolation=cv2.INTER_LINEAR)
    v, u = np.mgrid[0:size, 0:size] + 0.5
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T           # z = 1
    poses, images = [], []
    for x in xs:
        T = np.eye(4)
        T[0, 3] = x
        X = T[:3, 3] + depth * rays                                                # on the plane
        maps = [((c + 1.0) / 2.0 * 256 - 0.5).astype(np.float32) for c in (X[..., 0], X[..., 1])]
        images.append(cv2.remap(texture, *maps, cv2.INTER_LINEAR))
        poses.append(T)
    return torch.as_tensor(np.stack(images)).permute(0, 3, 1, 2).float(), np.stack(poses), K


def plane_answer(size: int, depth: float, **answer):
    """A random model's ``render_target`` of the last camera of ``textured_plane`` from the first
    five, with ``answer`` (``sweep=`` or ``oracle_depth=``), and the scene's geometry."""
    from iris_train.model import Scene
    images, poses, K = textured_plane(size, depth)
    model = random_model("tiny-rgb", image_height=size, image_width=size, samples=64)
    scene = Scene(torch.zeros(5, 1, 8, 8), torch.as_tensor(poses[:5]).float(),
                  torch.tensor([1.2, 1.2]), (size, size), images[:5])
    v, u = np.mgrid[0:size, 0:size] + 0.5
    origins, directions = NG.rays_from_pixels(np.stack([u, v], -1).reshape(-1, 2), K, poses[5])
    return (WB.render_target(model, scene, poses[5], **answer), images[5], poses, K,
            origins, directions)


def test_the_sweep_finds_a_textured_plane():
    """The plane sweep of a fronto-parallel textured plane seen by five cameras spread sideways:
    its weights sum to one where two views see the ray, and their depth lies on the plane to
    within the ±5% band on almost every ray whose band spans a pixel."""
    size, depth = 64, 0.6
    (rgb, weights, z, soft), _, poses, K, origins, directions = plane_answer(size, depth,
                                                                            sweep=(1e-4, 0))
    seen = weights.sum(-1) > 0
    np.testing.assert_allclose(weights.sum(-1)[seen], 1.0, atol=1e-5)
    true = depth * np.ones(size * size)
    par = WB.band_parallax(origins, directions, true, poses[:5], np.stack([K] * 5), size, size)
    sharp = seen & (par >= 1.0)
    assert sharp.mean() > 0.5
    assert (np.abs(soft - true)[sharp] <= WB.NEAR_BAND * depth).mean() > 0.95


def test_the_oracle_renders_the_plane_from_the_photos():
    """At the true depth the blend of the photos is the target photo (to bilinear sampling),
    whatever the random model's weights; the weights are one-hot at the nearest sample."""
    size, depth = 64, 0.6
    (rgb, weights, z, soft), target, *_ = plane_answer(size, depth,
                                                       oracle_depth=np.full(size * size, depth))
    np.testing.assert_array_equal(weights.max(-1), 1.0)
    np.testing.assert_array_equal(weights.sum(-1), 1.0)
    assert np.abs(soft - depth).max() <= (z[0, 1] - z[0, 0]) / 2 + 1e-6
    gt = target.permute(1, 2, 0).reshape(-1, 3).numpy()
    # The nearest sample is 0.0008 off the plane (0.002 here; 0.011 at a depth 3% off).
    assert np.abs(rgb - gt).mean() < 0.005


def test_the_oracle_at_the_output_size_beats_a_random_model():
    """``oracle_at_size`` of a textured plane's scene at 32x32 (the photos' size; the model's is
    16): the plane fills every view, so the oracle answers nearly every pixel, from the photos,
    far above a random model's render scaled up."""
    model = random_model("tiny-rgb", image_height=SIZE, image_width=SIZE, samples=8)
    record = WB.oracle_at_size(model, plane_scene(size=2 * SIZE), 2 * SIZE)
    assert record["used"] > 0.9
    assert record["oracle"] > record["upsampled"] + 5.0
    assert np.isfinite([record[k] for k in ("upsampled_used", "oracle_used")]).all()

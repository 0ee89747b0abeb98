"""benchmarks/wide_baseline.py: the angle of a hand-built geometry, the depth error against the
true depth itself, and one tiny scene rendered at its true cameras (weights, the eval's numbers,
the bins partitioning the rays)."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from benchmarks import wide_baseline as WB  # noqa: E402

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
    assert [r["bin"] for r in rows] == [*WB.BIN_NAMES, "all"]
    assert sum(r["rays"] for r in rows[:-1]) == rows[-1]["rays"] == len(targets) * SIZE * SIZE
    assert rows[WB.BIN_NAMES.index("no depth")]["rays"] == 0          # the plane fills every view
    assert np.all(rays["angle"][np.isfinite(rays["angle"])] < 10.0)    # cameras a few degrees apart
    # PSNR and depth Spearman as iris-eval computes them with the true cameras (Seq order).
    seq = evaluate(model, [scene], progress=False, cameras="true")["seq"]["scenes"][0]["model"]
    assert record["psnr"] == seq["psnr"] and record["depth_spearman"] == seq["depth_spearman"]

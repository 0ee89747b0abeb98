"""The geometric training signals for the cameras: epipolar pseudo-poses, their losses, and the
explicit image-based renderers. Checked against the true cameras of rendered scenes (which the
training code never reads) and against closed-form cases."""
from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("pyrender")
pytestmark = pytest.mark.torch

from iris_train import geometry as G  # noqa: E402
from iris_train import ibr, pseudo_poses  # noqa: E402
from iris_train.data import relative_to_first  # noqa: E402
from iris_train.synthetic import render_scene  # noqa: E402
from iris_train.losses import teacher_losses  # noqa: E402
from iris_train.metrics import psnr  # noqa: E402


@pytest.fixture(scope="module")
def scene():
    return render_scene(1_000_003, n_views=8, size=(64, 64))


def _random_poses(rng, n):
    out = np.tile(np.eye(4), (n, 1, 1))
    for k in range(1, n):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        out[k, :3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                          [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                          [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
        out[k, :3, 3] = rng.normal(size=3)
    return out


def test_teacher_rotations_are_accurate_on_a_rendered_scene(scene):
    pp = pseudo_poses.estimate(scene.images)
    V = scene.images.shape[0]
    iu = np.triu_indices(V, 1)
    assert pp.trusted[iu].mean() >= 0.5                       # most pairs overlap enough
    err = pseudo_poses.pair_errors(pp, scene.world_from_cam)
    trusted = err[:, 0] < 180
    assert np.median(err[trusted, 0]) < 8.0                   # rotation: the signal it is for
    assert np.median(err[trusted, 1]) < 30.0                  # translation direction: weaker
    assert 0.6 <= pp.focal <= 1.6
    # Structure: [j, i] is the inverse of [i, j], translations are unit, the diagonal is I.
    for i, j in zip(*iu):
        np.testing.assert_allclose(pp.cam_from_cam[j, i] @ pp.cam_from_cam[i, j], np.eye(4), atol=1e-9)
        if pp.trusted[i, j]:
            assert abs(np.linalg.norm(pp.cam_from_cam[i, j][:3, 3]) - 1) < 1e-9
    np.testing.assert_array_equal(pp.trusted, pp.trusted.T)
    assert not pp.trusted.diagonal().any()
    # Deterministic: the same images give the same teacher.
    again = pseudo_poses.estimate(scene.images)
    np.testing.assert_array_equal(again.cam_from_cam, pp.cam_from_cam)


def test_teacher_losses_vanish_at_the_teacher_and_pull_towards_it():
    rng = np.random.default_rng(0)
    world_from_cam = _random_poses(rng, 5)
    V = len(world_from_cam)
    cam_from_cam = np.empty((V, V, 4, 4))
    for a in range(V):
        for b in range(V):
            T = np.linalg.inv(world_from_cam[b]) @ world_from_cam[a]       # b <- a
            n = np.linalg.norm(T[:3, 3])
            T[:3, 3] /= max(n, 1e-12)
            cam_from_cam[a, b] = T
    trusted = ~np.eye(V, dtype=bool)
    args = (torch.as_tensor(cam_from_cam), torch.as_tensor(trusted), 0.9)
    at_teacher = teacher_losses(torch.as_tensor(world_from_cam), torch.tensor([0.9, 0.9], dtype=torch.float64), *args)
    assert float(at_teacher["teacher_rot"]) < 1e-12
    assert float(at_teacher["teacher_dir"]) < 1e-5           # the 1e-6 softening of |t|
    assert float(at_teacher["teacher_focal"]) < 1e-12
    # A perturbed view 2: both losses grow, and their gradient moves it back.
    pose = torch.as_tensor(world_from_cam).clone()
    angle = math.radians(10)
    turn = torch.tensor([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0],
                         [0, 0, 1]], dtype=torch.float64)
    pose[2, :3, :3] = turn @ pose[2, :3, :3]
    pose[2, :3, 3] += torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    pose.requires_grad_(True)
    out = teacher_losses(pose, torch.tensor([0.9, 0.9], dtype=torch.float64), *args)
    assert float(out["teacher_rot"].detach()) > 1e-3 and float(out["teacher_dir"].detach()) > 1e-3
    (out["teacher_rot"] + out["teacher_dir"]).backward()
    assert pose.grad[2].abs().sum() > 0
    assert pose.grad[[0, 1, 3, 4]].abs().sum() > 0            # pairs tie every view in


def test_untrusted_pairs_carry_no_loss():
    V = 3
    cam_from_cam = torch.tensor(_random_poses(np.random.default_rng(1), V * V).reshape(V, V, 4, 4))
    poses = torch.tensor(_random_poses(np.random.default_rng(2), V), requires_grad=True)
    out = teacher_losses(poses, torch.tensor([1.0, 1.0], dtype=torch.float64), cam_from_cam,
                         torch.zeros(V, V, dtype=torch.bool), 1.0)
    assert float(out["teacher_rot"].detach()) == 0 and float(out["teacher_dir"].detach()) == 0


def test_plane_sweep_prefers_the_true_cameras(scene):
    """The parameter-free renderer is better at the true cameras than at collapsed ones (the
    reason it is a signal the learned renderer cannot co-adapt away)."""
    images = torch.as_tensor(scene.images).permute(0, 3, 1, 2).double() / 255.0
    true = torch.as_tensor(relative_to_first(scene.world_from_cam))
    K = torch.as_tensor(scene.K)
    refs, target = [0, 2, 3, 5, 7], 4
    H, W = images.shape[-2:]
    uv = G.pixel_centres(H, W, dtype=torch.float64)
    depths = G.sample_depths(0.1, 1.0, 64, H * W, dtype=torch.float64)
    gt = images[target].permute(1, 2, 0).numpy()

    def score(poses):
        o, d = G.rays_from_pixels(uv, K, poses[target])
        rgb = ibr.plane_sweep_render(images[refs], poses[refs], K, o, d, depths, tau=0.01)
        return psnr(rgb.reshape(H, W, 3).clamp(0, 1).numpy(), gt)

    identity = torch.eye(4, dtype=torch.float64).expand(8, 4, 4).clone()
    assert score(true) > score(identity) + 1.5


def test_blend_render_uses_only_seen_samples_and_is_finite():
    logits = torch.tensor([[0.0, 50.0, -1e4], [1e4, 0.0, 0.0]])
    mean = torch.tensor([[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]]).expand(2, 3, 3)
    count = torch.tensor([[1.0, 0.0, 2.0], [0.0, 0.0, 0.0]])
    rgb = ibr.blend_render(logits, mean, count)
    assert torch.isfinite(rgb).all()
    torch.testing.assert_close(rgb[0], torch.tensor([1.0, 0, 0]))      # sample 1 unseen, 2 tiny
    torch.testing.assert_close(rgb[1], torch.zeros(3))                 # a ray that sees nothing


def test_blur_keeps_constants_and_mean():
    x = torch.full((2, 3, 16, 16), 0.3, dtype=torch.float64)
    torch.testing.assert_close(ibr.blur(x), x)
    y = torch.rand(1, 3, 32, 32, dtype=torch.float64)
    assert abs(float(ibr.blur(y).mean() - y.mean())) < 0.02
    assert float(ibr.blur(y).std()) < float(y.std())

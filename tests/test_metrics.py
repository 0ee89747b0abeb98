"""iris_train.metrics: PSNR/SSIM against scikit-image; pose errors against hand-made cameras and a
plain per-pair reference implementation of the paper's appendix."""
from __future__ import annotations

import itertools
import os
import subprocess
import sys

import numpy as np
import pytest

from iris_train.metrics import PSNR_CAP, capped_psnr, psnr, relative_pose_errors, rpa, ssim

skm = pytest.importorskip("skimage.metrics")


# ----------------------------------------------------------------------------------------------
# Images
# ----------------------------------------------------------------------------------------------

def _image_pairs():
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:48, 0:40] / 40.0
    ramp = np.stack([xx, yy, 0.5 * (xx + yy)], axis=-1) / np.stack([xx, yy, 0.5 * (xx + yy)], -1).max()
    checker = np.repeat(((np.indices((48, 40)).sum(0) // 4) % 2)[..., None], 3, -1).astype(float)
    noise = rng.random((48, 40, 3))
    return {
        "random": (rng.random((32, 32, 3)), rng.random((32, 32, 3))),
        "noisy-ramp": (np.clip(ramp + 0.05 * rng.standard_normal(ramp.shape), 0, 1), ramp),
        "checker-shift": (np.roll(checker, 1, axis=1), checker),
        "checker-vs-noise": (checker, noise),
        "constant": (np.full((20, 24, 3), 0.3), np.full((20, 24, 3), 0.7)),
        "constant-vs-ramp": (np.full((48, 40, 3), 0.5), ramp),
        "odd-size-minimum": (rng.random((11, 13, 3)), rng.random((11, 13, 3))),
        "float32": (rng.random((16, 16, 3)).astype(np.float32), rng.random((16, 16, 3)).astype(np.float32)),
    }


@pytest.mark.parametrize("name", list(_image_pairs()))
def test_psnr_ssim_match_scikit_image(name):
    pred, gt = _image_pairs()[name]
    ref_ssim = skm.structural_similarity(pred.astype(np.float64), gt.astype(np.float64),
                                         channel_axis=-1, data_range=1.0, gaussian_weights=True,
                                         sigma=1.5, use_sample_covariance=False)
    assert abs(ssim(pred, gt) - ref_ssim) < 1e-6
    ref_psnr = skm.peak_signal_noise_ratio(gt.astype(np.float64), pred.astype(np.float64), data_range=1.0)
    assert abs(psnr(pred, gt) - ref_psnr) < 1e-6


def test_image_metric_edge_cases():
    a = np.random.default_rng(1).random((16, 16, 3))
    assert psnr(a, a) == float("inf")
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    assert psnr(a * 255, np.clip(a * 255 + 1, 0, 255), data_range=255) == pytest.approx(
        skm.peak_signal_noise_ratio(np.clip(a * 255 + 1, 0, 255), a * 255, data_range=255))
    with pytest.raises(ValueError, match="same shape"):
        psnr(a, a[:8])
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(a[:10, :10], a[:10, :10])
    assert capped_psnr(a, a) == PSNR_CAP == 100.0
    b = np.clip(a + 0.01, 0, 1)
    assert capped_psnr(a, b) == psnr(a, b) < PSNR_CAP


# ----------------------------------------------------------------------------------------------
# Poses
# ----------------------------------------------------------------------------------------------

def rot(axis, deg):
    """Rotation matrix about ``axis`` by ``deg`` degrees (Rodrigues)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = np.radians(deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def pose(R=np.eye(3), c=(0, 0, 0)):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c
    return T


def ring(n=6, radius=2.0, height=0.5):
    """n cameras on a circle looking at the origin (OpenCV axes: z forward, y down)."""
    out = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        c = np.array([radius * np.cos(a), radius * np.sin(a), height])
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0.0, 0.0, 1.0])      # y = z x x then points down
        x /= np.linalg.norm(x)
        out.append(pose(np.stack([x, np.cross(z, x), z], axis=1), c))
    return np.stack(out)


def random_poses(rng, n):
    Q, _ = np.linalg.qr(rng.standard_normal((n, 3, 3)))
    Q *= np.sign(np.linalg.det(Q))[:, None, None]
    return np.stack([pose(Q[k], rng.standard_normal(3)) for k in range(n)])


def similarity(T, R, t, s):
    """Apply the world similarity x -> s R x + t to camera-to-world poses (stays rigid)."""
    out = T.copy()
    out[:, :3, :3] = R @ T[:, :3, :3]
    out[:, :3, 3] = s * T[:, :3, 3] @ R.T + t
    return out


def reference_errors(pred, gt):
    """The appendix, literally, one pair at a time (general matrix inverses, arccos)."""
    rots, trans = [], []
    for i, j in itertools.combinations(range(len(gt)), 2):
        Th = np.linalg.inv(pred[i]) @ np.linalg.inv(np.linalg.inv(pred[j]))
        T = np.linalg.inv(gt[i]) @ np.linalg.inv(np.linalg.inv(gt[j]))
        c = (np.trace(T[:3, :3].T @ Th[:3, :3]) - 1) / 2
        rots.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
        ct = T[:3, 3] @ Th[:3, 3] / (np.linalg.norm(T[:3, 3]) * np.linalg.norm(Th[:3, 3]))
        a = np.degrees(np.arccos(np.clip(ct, -1, 1)))
        trans.append(min(a, 180 - a))
    return np.array(rots), np.array(trans)


def test_matches_plain_reference_on_random_poses():
    rng = np.random.default_rng(0)
    gt = random_poses(rng, 7)
    pred = random_poses(rng, 7)
    pred[:, :3, :3] += 1e-4 * rng.standard_normal((7, 3, 3))    # not exactly orthonormal
    r, t = relative_pose_errors(pred, gt)
    r_ref, t_ref = reference_errors(pred, gt)
    assert r.shape == t.shape == (21,)
    np.testing.assert_allclose(r, r_ref, atol=1e-9)
    np.testing.assert_allclose(t, t_ref, atol=1e-9)
    assert (r >= 0).all() and (r <= 180).all() and (t >= 0).all() and (t <= 90).all()


def test_identical_poses_have_zero_error():
    gt = ring(6)
    r, t = relative_pose_errors(gt, gt)
    assert np.abs(r).max() < 1e-5 and np.abs(t).max() < 1e-5
    assert rpa(gt, gt) == {"rpa@5": 1.0, "rpa@15": 1.0, "rpa@30": 1.0}


@pytest.mark.parametrize("axis", [(0, 0, 1), (1, 0, 0), (1, 2, -1)])
def test_rotating_one_camera_gives_known_rotation_error(axis):
    gt = ring(5)
    pred = gt.copy()
    pred[-1, :3, :3] = gt[-1, :3, :3] @ rot(axis, 10.0)     # turn the last camera in place by 10 deg
    r, t = relative_pose_errors(pred, gt)
    i, j = np.triu_indices(5, 1)
    with_last = j == 4
    np.testing.assert_allclose(r[with_last], 10.0, atol=1e-6)
    np.testing.assert_allclose(r[~with_last], 0.0, atol=1e-5)
    # T_{i<-4}'s translation is R_i^T (c_4 - c_i): independent of camera 4's rotation.
    np.testing.assert_allclose(t, 0.0, atol=1e-5)
    n_pairs, n_last = len(r), with_last.sum()
    assert rpa(pred, gt) == {"rpa@5": (n_pairs - n_last) / n_pairs, "rpa@15": 1.0, "rpa@30": 1.0}


@pytest.mark.parametrize("angle, expected", [(20.0, 20.0), (70.0, 70.0), (110.0, 70.0),
                                             (160.0, 20.0), (180.0, 0.0)])
def test_translation_direction_error_is_sign_ambiguous(angle, expected):
    gt = np.stack([pose(), pose(c=(1.0, 0.0, 0.0))])
    pred = np.stack([pose(), pose(c=3.0 * rot((0, 0, 1), angle)[:, 0])])   # other length too
    r, t = relative_pose_errors(pred, gt)
    np.testing.assert_allclose(r, 0.0, atol=1e-6)
    np.testing.assert_allclose(t, expected, atol=1e-6)
    assert rpa(pred, gt, thresholds=(expected + 1,)) == {f"rpa@{expected + 1:g}": 1.0}
    if expected > 1:
        assert rpa(pred, gt, thresholds=(expected - 1,))[f"rpa@{expected - 1:g}"] == 0.0


def test_pose_error_is_max_of_rotation_and_translation():
    gt = np.stack([pose(), pose(c=(1.0, 0.0, 0.0))])
    pred = np.stack([pose(), pose(rot((0, 1, 0), 8.0), c=rot((0, 0, 1), 20.0)[:, 0])])
    r, t = relative_pose_errors(pred, gt)
    assert r[0] == pytest.approx(8.0) and t[0] == pytest.approx(20.0)
    assert rpa(pred, gt, thresholds=(10, 19, 21)) == {"rpa@10": 0.0, "rpa@19": 0.0, "rpa@21": 1.0}


def test_invariant_to_similarity_of_predicted_and_true_world():
    rng = np.random.default_rng(3)
    gt = ring(8)
    pred = gt.copy()
    for k in range(8):      # perturb: rotations by a few degrees, centres by a bit
        pred[k, :3, :3] = gt[k, :3, :3] @ rot(rng.standard_normal(3), rng.uniform(0, 25))
        pred[k, :3, 3] += 0.3 * rng.standard_normal(3)
    r0, t0 = relative_pose_errors(pred, gt)
    for s in (1e-3, 0.5, 7.0, 1e4):
        R = rot(rng.standard_normal(3), rng.uniform(0, 180))
        tr = 10 * rng.standard_normal(3)
        r1, t1 = relative_pose_errors(similarity(pred, R, tr, s), gt)
        np.testing.assert_allclose(r1, r0, atol=1e-6)
        np.testing.assert_allclose(t1, t0, atol=1e-6)
        r2, t2 = relative_pose_errors(pred, similarity(gt, R, tr, s))
        np.testing.assert_allclose(r2, r0, atol=1e-6)
        np.testing.assert_allclose(t2, t0, atol=1e-6)
        assert rpa(similarity(pred, R, tr, s), gt) == rpa(pred, gt)
    # Re-basing to view 0 (the model's canonical frame) is a rigid change of world frame.
    rebased = np.linalg.inv(pred[0]) @ pred
    np.testing.assert_allclose(relative_pose_errors(rebased, gt)[0], r0, atol=1e-6)


def test_zero_translation_convention():
    # Pure rotations about a common centre: ground-truth relative translations are zero.
    centre = np.array([0.4, -1.0, 2.0])
    gt = np.stack([pose(rot((0, 1, 0), a), centre) for a in (0.0, 3.0, 12.0, 40.0)])
    # Both zero -> 0 deg: e_pose is the rotation error; identity poses score |yaw_i - yaw_j|.
    r, t = relative_pose_errors(np.broadcast_to(np.eye(4), gt.shape), gt)
    np.testing.assert_allclose(t, 0.0)
    np.testing.assert_allclose(r, [3, 12, 40, 9, 37, 28], atol=1e-6)
    assert rpa(np.broadcast_to(np.eye(4), gt.shape), gt) == {"rpa@5": 1 / 6, "rpa@15": 3 / 6,
                                                           "rpa@30": 4 / 6}
    # Survives a similarity of the world (rounding noise is not a direction).
    g2 = similarity(gt, rot((1, 1, 0), 33.0), np.array([5.0, 6.0, -7.0]), 3.0)
    np.testing.assert_allclose(relative_pose_errors(gt, g2)[1], 0.0)
    # Exactly one zero -> 90 deg, whichever side it is on.
    moved = gt.copy()
    moved[1:, :3, 3] += np.array([0.0, 0.0, 1.0]) * np.arange(1, 4)[:, None]
    assert (relative_pose_errors(moved, gt)[1][:3] == 90.0).all()
    assert (relative_pose_errors(gt, moved)[1][:3] == 90.0).all()
    # Identity poses against translating cameras: no credit at all.
    assert rpa(np.broadcast_to(np.eye(4), (6, 4, 4)), ring(6)) == {"rpa@5": 0.0, "rpa@15": 0.0,
                                                                   "rpa@30": 0.0}


def test_pose_input_checks():
    gt = ring(3)
    with pytest.raises(ValueError, match=r"\[B, 4, 4\]"):
        relative_pose_errors(gt[:, :3], gt)
    with pytest.raises(ValueError, match="same number"):
        relative_pose_errors(gt[:2], gt)
    with pytest.raises(ValueError, match="at least 2"):
        relative_pose_errors(gt[:1], gt[:1])
    bad = gt.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        rpa(bad, gt)


def test_metrics_module_does_not_import_torch():
    # iris_train/__init__ imports torch; load metrics.py on its own, as the runtime path would.
    code = ("import importlib.util, sys; "
            "spec = importlib.util.spec_from_file_location('m', 'iris_train/metrics.py'); "
            "m = importlib.util.module_from_spec(spec); spec.loader.exec_module(m); "
            "sys.exit(1 if 'torch' in sys.modules else 0)")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    assert subprocess.run([sys.executable, "-c", code], cwd=root).returncode == 0


# ----------------------------------------------------------------------------------------------
# Depth rank correlation
# ----------------------------------------------------------------------------------------------

def _depth_pairs():
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:24, 0:20] / 20.0
    true = 0.3 + 0.5 * xx + 0.1 * yy
    hole = true.copy()
    hole[5:12, 3:9] = 0.0                                  # no geometry there
    quantised = np.round(true * 8) / 8                    # many ties in the truth
    distinct = 0.2 + rng.random((24, 20))                 # no ties
    return {
        "monotone": (np.exp(3 * distinct), distinct),      # any monotone map: exactly 1
        "reversed": (-distinct, distinct),
        "noisy-with-holes": (hole + 0.05 * rng.standard_normal(hole.shape), hole),
        "ties-both": (np.round(hole * 4) / 4, quantised),
        "random": (rng.random((16, 16)), rng.random((16, 16)) + 0.1),
        "float32": (rng.random((8, 9)).astype(np.float32), (rng.random((8, 9)) + 0.1).astype(np.float32)),
    }


@pytest.mark.parametrize("name", list(_depth_pairs()))
def test_depth_spearman_matches_scipy(name):
    stats = pytest.importorskip("scipy.stats")
    from iris_train.metrics import depth_spearman
    pred, true = _depth_pairs()[name]
    valid = true > 0
    expected = stats.spearmanr(pred[valid], true[valid]).statistic
    assert depth_spearman(pred, true) == pytest.approx(expected, abs=1e-12)
    if name == "monotone":
        assert depth_spearman(pred, true) == pytest.approx(1.0, abs=1e-12)
    if name == "reversed":
        assert depth_spearman(pred, true) == pytest.approx(-1.0, abs=1e-12)


def test_depth_spearman_ignores_pixels_without_geometry_and_non_finite_predictions():
    from iris_train.metrics import depth_spearman
    true = np.array([[0.0, 0.5, 0.6], [0.7, 0.0, 0.8]])
    pred = np.array([[9.0, 1.0, 2.0], [3.0, -9.0, 4.0]])
    assert depth_spearman(pred, true) == pytest.approx(1.0)
    pred_nan = pred.copy()
    pred_nan[0, 0] = np.nan                                # on a pixel without geometry: irrelevant
    pred_nan[1, 2] = np.inf                                # on a valid pixel: left out
    assert depth_spearman(pred_nan, true) == pytest.approx(1.0)


def test_depth_spearman_is_nan_when_undefined():
    import warnings

    from iris_train.metrics import depth_spearman
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(depth_spearman(np.ones((4, 4)), np.zeros((4, 4))))            # no geometry
        two = np.zeros((4, 4))
        two[0, :2] = (0.5, 0.6)
        assert np.isnan(depth_spearman(np.random.default_rng(0).random((4, 4)), two))  # 2 pixels
        true = np.linspace(0.2, 0.9, 16).reshape(4, 4)
        assert np.isnan(depth_spearman(np.full((4, 4), 0.5), true))                   # constant pred
        assert np.isnan(depth_spearman(true, np.full((4, 4), 0.5)))                   # constant truth
        assert np.isnan(depth_spearman(np.full((4, 4), np.nan), true))                # all NaN
    with pytest.raises(ValueError):
        depth_spearman(np.ones((4, 4)), np.ones((4, 5)))
    with pytest.raises(ValueError):
        depth_spearman(np.ones(4), np.ones(4))

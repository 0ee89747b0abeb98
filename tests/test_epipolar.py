"""iris_runtime.epipolar: two-view geometry, the global camera solve, the refinement of a model's
cameras and ``IrisRuntime.encode(images, cameras="epipolar")``.

The first half is numpy + OpenCV only (synthetic relative poses and correspondences, runs
torch-free); the second half renders a synthetic scene (``iris_train.synthetic``, marked torch)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from iris_runtime import epipolar as E
from iris_runtime.errors import InputError

REPO = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------

def _rotation(rng, max_angle=np.pi):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(-max_angle, max_angle)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _random_cameras(rng, n, max_angle=np.pi):
    """Random rigid world_from_cam [n, 4, 4] re-based so that view 0 = I."""
    T = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        T[k, :3, :3] = _rotation(rng, max_angle)
        T[k, :3, 3] = rng.normal(size=3)
    return np.linalg.inv(T[0]) @ T


def _exact_pairwise(world_from_cam, trusted=None, inliers=500) -> E.PairwisePoses:
    """The relative poses of true cameras: cam_from_cam[i, j] = cam_from_world_j @ world_from_cam_i
    with the translation made unit, as the essential matrix gives them."""
    V = len(world_from_cam)
    cfc = np.tile(np.eye(4), (V, V, 1, 1))
    for i in range(V):
        for j in range(V):
            if i != j:
                T = np.linalg.inv(world_from_cam[j]) @ world_from_cam[i]
                T[:3, 3] /= np.linalg.norm(T[:3, 3])
                cfc[i, j] = T
    if trusted is None:
        trusted = ~np.eye(V, dtype=bool)
    inl = np.where(trusted, inliers, 0).astype(np.int32)
    return E.PairwisePoses(cfc, np.asarray(trusted, bool), inl, 1.0)


def _rotation_errors_deg(A, B):
    cos = (np.einsum("kij,kij->k", A[:, :3, :3], B[:, :3, :3]) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def _fitted_centres(solved, truth):
    """Solved centres scaled by least squares onto the true ones (the solve has no unit)."""
    c, t = solved[:, :3, 3], truth[:, :3, 3]
    s = np.sum(c * t) / np.sum(c * c)
    return s, s * c


# ----------------------------------------------------------------------------------------------
# global solve from pairwise poses (numpy only)
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("robust", [True, False])
@pytest.mark.parametrize("translation", E.TRANSLATION_SOLVERS)
def test_global_solve_recovers_exact_cameras(seed, robust, translation):
    rng = np.random.default_rng(seed)
    truth = _random_cameras(rng, 6)
    pp = _exact_pairwise(truth)
    sol = E.solve_global(pp, robust=robust, translation=translation)
    T = sol.world_from_cam
    assert sol.solved.all() and T.shape == (6, 4, 4)
    np.testing.assert_array_equal(T[0], np.eye(4))
    np.testing.assert_allclose(T[:, :3, :3], truth[:, :3, :3], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(T[:, :3, 3]), 1.0, atol=1e-12)   # unit-free
    s, c = _fitted_centres(T, truth)
    assert s > 0                                             # the sign vote got the sign right
    np.testing.assert_allclose(c, truth[:, :3, 3], atol=1e-9)
    np.testing.assert_allclose(T[:, 3], np.tile([0, 0, 0, 1.0], (6, 1)), atol=0)
    assert sol.translation_gap < 1e-6                        # a well-posed translation problem
    np.testing.assert_array_equal(E.solve_cameras(pp, robust=robust, translation=translation), T)


@pytest.mark.parametrize("translation", E.TRANSLATION_SOLVERS)
def test_global_solve_flags_ill_posed_centres_and_bad_arguments(translation):
    rng = np.random.default_rng(10)
    truth = _random_cameras(rng, 3)
    chain = np.zeros((3, 3), bool)
    chain[0, 1] = chain[1, 0] = chain[1, 2] = chain[2, 1] = True   # two independent baselines
    sol = E.solve_global(_exact_pairwise(truth, chain), translation=translation)
    assert sol.solved.all() and sol.translation_gap == 1.0
    np.testing.assert_allclose(sol.world_from_cam[:, :3, :3], truth[:, :3, :3], atol=1e-9)
    with pytest.raises(ValueError, match="translation"):
        E.solve_global(_exact_pairwise(truth), translation="svd")


def test_global_solve_with_a_sparse_but_rigid_graph_and_two_views():
    rng = np.random.default_rng(5)
    truth = _random_cameras(rng, 5)
    trusted = np.zeros((5, 5), bool)
    for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (0, 2), (1, 3), (2, 4)]:   # triangles
        trusted[i, j] = trusted[j, i] = True
    T = E.solve_cameras(_exact_pairwise(truth, trusted))
    np.testing.assert_allclose(T[:, :3, :3], truth[:, :3, :3], atol=1e-9)
    np.testing.assert_allclose(_fitted_centres(T, truth)[1], truth[:, :3, 3], atol=1e-9)
    # Two views: the direction of the one baseline, with its sign.
    T2 = E.solve_cameras(_exact_pairwise(truth[:2]))
    np.testing.assert_allclose(T2[1, :3, 3], truth[1, :3, 3] / np.linalg.norm(truth[1, :3, 3]),
                               atol=1e-12)


def test_global_solve_is_robust_to_a_few_corrupted_pairs():
    rng = np.random.default_rng(3)
    truth = _random_cameras(rng, 8, max_angle=0.5)
    pp = _exact_pairwise(truth)
    cfc = pp.cam_from_cam.copy()
    for i, j in [(0, 5), (2, 3), (4, 7)]:              # 3 of 28 pairs: wrong by 30-90 degrees
        T = np.eye(4)
        T[:3, :3] = _rotation(rng, np.pi / 2) @ cfc[i, j][:3, :3]
        t = rng.normal(size=3)
        T[:3, 3] = t / np.linalg.norm(t)
        cfc[i, j], cfc[j, i] = T, np.linalg.inv(T)
    bad = E.PairwisePoses(cfc, pp.trusted, pp.inliers, 1.0)
    robust = E.solve_cameras(bad)
    plain = E.solve_cameras(bad, robust=False)
    err_robust = _rotation_errors_deg(robust, truth)
    err_plain = _rotation_errors_deg(plain, truth)
    assert err_robust.max() < 1.0, err_robust
    assert err_robust.max() < err_plain.max()
    # Translation: still the right sign and the right shape on the whole.
    s, c = _fitted_centres(robust, truth)
    assert s > 0
    cos = np.sum(c[1:] * truth[1:, :3, 3], axis=1) / (
        np.linalg.norm(c[1:], axis=1) * np.linalg.norm(truth[1:, :3, 3], axis=1))
    assert np.median(np.degrees(np.arccos(np.clip(cos, -1, 1)))) < 10


def test_disconnected_graph_solves_the_component_of_view_0_only():
    rng = np.random.default_rng(4)
    truth = _random_cameras(rng, 6)
    trusted = np.zeros((6, 6), bool)
    for i, j in [(0, 1), (1, 2), (0, 2), (3, 4), (4, 5), (3, 5)]:   # {0, 1, 2} and {3, 4, 5}
        trusted[i, j] = trusted[j, i] = True
    pp = _exact_pairwise(truth, trusted)
    np.testing.assert_array_equal(E.reachable_views(trusted), [1, 1, 1, 0, 0, 0])
    sol = E.solve_global(pp)
    np.testing.assert_array_equal(sol.solved, [1, 1, 1, 0, 0, 0])
    assert np.isnan(sol.world_from_cam[3:]).all()
    np.testing.assert_allclose(sol.world_from_cam[:3, :3, :3], truth[:3, :3, :3], atol=1e-9)
    np.testing.assert_allclose(_fitted_centres(sol.world_from_cam[:3], truth[:3])[1],
                               truth[:3, :3, 3], atol=1e-9)
    # Nothing trusted: only view 0, the identity.
    none = E.solve_global(_exact_pairwise(truth, np.zeros((6, 6), bool)))
    np.testing.assert_array_equal(none.solved, [1, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(none.world_from_cam[0], np.eye(4))


# ----------------------------------------------------------------------------------------------
# scale fit and refine_cameras' fallbacks (numpy only: the pairwise poses are given)
# ----------------------------------------------------------------------------------------------

def test_fit_scale_least_squares_and_its_fallbacks():
    rng = np.random.default_rng(6)
    ce = rng.normal(size=(5, 3))
    ce[0] = 0
    s, how = E.fit_scale(0.3 * ce, ce)
    assert how == "fit" and s == pytest.approx(0.3, rel=1e-12)
    noisy = 0.3 * ce + 0.01 * rng.normal(size=ce.shape)
    s, _ = E.fit_scale(noisy, ce)
    assert s == pytest.approx(np.sum(noisy * ce) / np.sum(ce * ce), rel=1e-12)
    # Opposed centres: the model's mean baseline instead (magnitude only).
    s, how = E.fit_scale(-0.3 * ce, ce)
    assert how == "baseline" and s == pytest.approx(0.3, rel=1e-12)
    # Collapsed model centres: the documented constant mean baseline.
    s, how = E.fit_scale(np.full((5, 3), 1e-9), ce)
    i, j = np.triu_indices(5, 1)
    assert how == "constant"
    assert s * np.linalg.norm(ce[i] - ce[j], axis=1).mean() == pytest.approx(E.DEFAULT_BASELINE)


def _refine_with(monkeypatch, pp, model_poses, focal=(0.9, 0.9), matches=None):
    """refine_cameras with the pairwise step replaced by ``pp`` and the flow by ``matches``
    (default: none, so the translations come from the directions alone; no images needed)."""
    monkeypatch.setattr(E, "pairwise_poses", lambda images, focal=None, **kw: pp)
    monkeypatch.setattr(E, "all_flow_matches", lambda images: {} if matches is None else matches)
    images = np.zeros((len(model_poses), 16, 16, 3), np.uint8)
    return E.refine_cameras(images, model_poses, np.asarray(focal), scale="model")


def test_refine_cameras_replaces_poses_in_the_model_units(monkeypatch):
    rng = np.random.default_rng(7)
    truth = _random_cameras(rng, 5, max_angle=0.3)
    model = np.tile(np.eye(4), (5, 1, 1))
    model[:, :3, 3] = 0.25 * truth[:, :3, 3]              # right centres in its own unit, no rotation
    pp = _exact_pairwise(truth)
    ref = _refine_with(monkeypatch, pp, model)
    assert ref.source == "epipolar" and ref.solved.all() and ref.scale_source == "fit"
    np.testing.assert_allclose(ref.world_from_cam[:, :3, :3], truth[:, :3, :3], atol=1e-9)
    np.testing.assert_allclose(ref.world_from_cam[:, :3, 3], model[:, :3, 3], atol=1e-9)
    np.testing.assert_array_equal(ref.world_from_cam[0], np.eye(4))
    # Focal: the pairwise step's (searched), fy/H from fx/W for these square images.
    np.testing.assert_allclose(ref.focal, [1.0, 1.0])


def test_refine_cameras_roots_the_solve_at_the_largest_trusted_set(monkeypatch):
    """View 0 without a trusted pair: the other four are solved among themselves, view 0 is
    located against them (here: a stand-in returning its true pose in their frame), and all is
    re-based on view 0."""
    rng = np.random.default_rng(9)
    truth = _random_cameras(rng, 5, max_angle=0.3)
    trusted = ~np.eye(5, dtype=bool)
    trusted[0, :] = trusted[:, 0] = False
    calls = []

    def locate_stub(refs, T_refs, focal, queries, **kw):
        calls.append(len(queries))
        # the solve's frame is view 1's, its unit |c| = 1 over views 1-4: map the truth into it
        frame = np.linalg.inv(truth[1]) @ truth[1:]
        s = np.linalg.norm(T_refs[:, :3, 3]) / np.linalg.norm(frame[:, :3, 3])
        q = np.linalg.inv(truth[1]) @ truth[0]
        q[:3, 3] *= s
        return q[None], np.ones(1, bool)
    monkeypatch.setattr(E, "locate_views", locate_stub)
    model = np.tile(np.eye(4), (5, 1, 1))
    model[:, :3, 3] = 0.3 * truth[:, :3, 3]
    ref = _refine_with(monkeypatch, _exact_pairwise(truth, trusted), model)
    assert calls == [1] and ref.source == "epipolar" and ref.solved.all()
    np.testing.assert_array_equal(ref.world_from_cam[0], np.eye(4))
    np.testing.assert_allclose(ref.world_from_cam[:, :3, :3], truth[:, :3, :3], atol=1e-9)
    np.testing.assert_allclose(ref.world_from_cam[:, :3, 3], model[:, :3, 3], atol=1e-9)


def test_refine_cameras_keeps_the_model_for_unreachable_views(monkeypatch):
    rng = np.random.default_rng(8)
    truth = _random_cameras(rng, 5, max_angle=0.3)
    model = np.tile(np.eye(4), (5, 1, 1))
    model[:, :3, 3] = 0.5 * truth[:, :3, 3] + 0.01
    model[0] = np.eye(4)
    trusted = np.zeros((5, 5), bool)
    for i, j in [(0, 1), (1, 2), (0, 2), (3, 4)]:
        trusted[i, j] = trusted[j, i] = True
    # Views 3 and 4 lie outside the largest trusted set and cannot be located either.
    monkeypatch.setattr(E, "locate_views", lambda refs, T, f, q, **kw:
                        (np.full((len(q), 4, 4), np.nan), np.zeros(len(q), bool)))
    ref = _refine_with(monkeypatch, _exact_pairwise(truth, trusted), model)
    assert ref.source == "mixed"
    np.testing.assert_array_equal(ref.solved, [1, 1, 1, 0, 0])
    np.testing.assert_array_equal(ref.world_from_cam[3:], model[3:])          # the model's
    np.testing.assert_allclose(ref.world_from_cam[:3, :3, :3], truth[:3, :3, :3], atol=1e-9)
    # Scale fitted over the solved views only.
    c = E.solve_cameras(_exact_pairwise(truth, trusted))[:3, :3, 3]
    assert ref.scale == pytest.approx(np.sum(model[:3, :3, 3] * c) / np.sum(c * c), rel=1e-9)
    # Nothing reached: the model's cameras and focal, unchanged.
    ref = _refine_with(monkeypatch, _exact_pairwise(truth, np.zeros((5, 5), bool)), model,
                       focal=(0.7, 0.6))
    assert ref.source == "model" and not ref.solved.any()
    np.testing.assert_array_equal(ref.world_from_cam, model)
    np.testing.assert_array_equal(ref.focal, [0.7, 0.6])


# ----------------------------------------------------------------------------------------------
# depths from correspondences: triangulation, baseline ties, scale to a depth range (numpy only)
# ----------------------------------------------------------------------------------------------

H_SYN = W_SYN = 64
F_SYN = 1.0                                        # fx / W


def _forward_cameras(rng, n, spread=0.15, max_angle=0.15):
    """n cameras looking down +z near the origin (view 0 = I), so a cloud at z in [2, 4] is in
    front of all of them."""
    T = np.tile(np.eye(4), (n, 1, 1))
    for k in range(1, n):
        T[k, :3, :3] = _rotation(rng, max_angle)
        T[k, :3, 3] = spread * rng.normal(size=3)
    return T


def _exact_matches(truth, rng, n_points=3000):
    """``{(i, j): (p, q)}`` for i < j: the projections of one point cloud seen by every view
    (pixels, centres at +0.5) and the points' depths ``z [V, N]`` in each camera."""
    X = np.stack([rng.uniform(-1.2, 1.2, n_points), rng.uniform(-1.2, 1.2, n_points),
                  rng.uniform(2.0, 4.0, n_points)], 1)
    K = E.intrinsics(F_SYN, H_SYN, W_SYN)
    pix, z = [], []
    for T in truth:
        Y = (X - T[:3, 3]) @ T[:3, :3]
        z.append(Y[:, 2])
        pix.append((Y @ K.T)[:, :2] / Y[:, 2:])
    pix, z = np.stack(pix), np.stack(z)
    seen = ((pix > 0.0) & (pix < W_SYN)).all(axis=(0, 2)) & (z > 0).all(0)
    V = len(truth)
    matches = {(i, j): (pix[i, seen], pix[j, seen]) for i in range(V) for j in range(i + 1, V)}
    return matches, z[:, seen]


def test_match_depths_are_the_true_depths():
    rng = np.random.default_rng(20)
    truth = _forward_cameras(rng, 4)
    matches, z = _exact_matches(truth, rng)
    d = E.match_depths(matches, truth, F_SYN, H_SYN, W_SYN, pairs=[(0, 1)])
    # Only the matches whose rays meet at under MIN_PARALLAX are left out.
    a = (matches[0, 1][0] - [W_SYN / 2, H_SYN / 2]) / (F_SYN * W_SYN)
    b = (matches[0, 1][1] - [W_SYN / 2, H_SYN / 2]) / (F_SYN * W_SYN)
    ra = np.c_[a, np.ones(len(a))] @ truth[0, :3, :3].T
    rb = np.c_[b, np.ones(len(b))] @ truth[1, :3, :3].T
    cos = (ra * rb).sum(1) / np.linalg.norm(ra, axis=1) / np.linalg.norm(rb, axis=1)
    enough = np.arccos(np.clip(cos, -1, 1)) > E.MIN_PARALLAX
    assert 0.5 * z.shape[1] < len(d) == enough.sum()
    np.testing.assert_allclose(d, z[0, enough], rtol=1e-9)
    # The depths of every pair, in its first camera; a view without a camera (NaN) is skipped.
    gone = truth.copy()
    gone[3] = np.nan
    every = E.match_depths(matches, gone, F_SYN, H_SYN, W_SYN)
    assert len(every) <= 3 * z.shape[1]            # pairs (0,1), (0,2), (1,2) only
    # Sparse depth maps: a pixel holding exactly one point has that point's depth.
    maps = E.reference_depths({(0, 1): matches[0, 1]}, truth, F_SYN, H_SYN, W_SYN)
    assert maps.shape == (4, H_SYN, W_SYN) and np.isnan(maps[2:]).all()
    p = matches[0, 1][0]
    cell = np.floor(p[:, 1]).astype(int) * W_SYN + np.floor(p[:, 0]).astype(int)
    single = np.flatnonzero((np.bincount(cell, minlength=H_SYN * W_SYN)[cell] == 1) & enough)
    np.testing.assert_allclose(maps[0].ravel()[cell[single]], z[0, single], rtol=1e-9)


def test_depth_ties_fix_the_baseline_of_a_view_with_one_pair():
    rng = np.random.default_rng(21)
    truth = _forward_cameras(rng, 5)
    matches, _ = _exact_matches(truth, rng)
    trusted = np.zeros((5, 5), bool)
    for i, j in [(0, 1), (0, 2), (1, 2), (2, 3), (3, 4)]:      # views 3 and 4 hang on one pair each
        trusted[i, j] = trusted[j, i] = True
    pp = _exact_pairwise(truth, trusted)
    pp = E.PairwisePoses(pp.cam_from_cam, pp.trusted, pp.inliers, F_SYN)
    tied = E.solve_global(pp, matches=matches, image_size=(H_SYN, W_SYN)).world_from_cam
    np.testing.assert_allclose(tied[:, :3, :3], truth[:, :3, :3], atol=1e-9)
    np.testing.assert_allclose(_fitted_centres(tied, truth)[1], truth[:, :3, 3], atol=1e-8)
    # Directions alone cannot fix those two lengths: the same solve without the ties is off.
    free = E.solve_cameras(pp)
    assert np.abs(_fitted_centres(free, truth)[1] - truth[:, :3, 3]).max() > 1e-3
    with pytest.raises(ValueError, match="image_size"):
        E.solve_global(pp, matches=matches)


def test_refine_cameras_scales_the_scene_into_the_depth_range(monkeypatch):
    rng = np.random.default_rng(22)
    truth = _forward_cameras(rng, 5)
    matches, _ = _exact_matches(truth, rng)
    pp = _exact_pairwise(truth)
    pp = E.PairwisePoses(pp.cam_from_cam, pp.trusted, pp.inliers, F_SYN)
    model = np.tile(np.eye(4), (5, 1, 1))
    monkeypatch.setattr(E, "pairwise_poses", lambda images, focal=None, **kw: pp)
    monkeypatch.setattr(E, "all_flow_matches", lambda images: matches)
    images = np.zeros((5, H_SYN, W_SYN, 3), np.uint8)
    ref = E.refine_cameras(images, model, [F_SYN, F_SYN], scale="depth", depth_range=(0.1, 1.0))
    assert ref.scale_source == "depth" and ref.source == "epipolar"
    d = E.match_depths(matches, ref.world_from_cam, F_SYN, H_SYN, W_SYN)
    assert np.median(d) == pytest.approx(0.1 + E.DEPTH_TARGET * 0.9, rel=1e-9)
    np.testing.assert_allclose(_fitted_centres(ref.world_from_cam, truth)[1], truth[:, :3, 3],
                               atol=1e-8)
    for bad in (None, (1.0, 0.1), (0.1, np.inf), (-1.0, 1.0)):
        with pytest.raises(ValueError, match="depth_range"):
            E.refine_cameras(images, model, [F_SYN, F_SYN], scale="depth", depth_range=bad)
    with pytest.raises(ValueError, match="scale"):
        E.refine_cameras(images, model, [F_SYN, F_SYN], scale="metric")


def test_refine_cameras_single_view_and_bad_arguments():
    one = E.refine_cameras(np.zeros((1, 8, 8, 3), np.uint8), np.eye(4)[None], [1.0, 1.0],
                           depth_range=(0.1, 1.0))
    assert one.source == "model"
    np.testing.assert_array_equal(one.world_from_cam, np.eye(4)[None])
    with pytest.raises(ValueError, match="images"):
        E.refine_cameras(np.zeros((2, 8, 8, 3), np.float32), np.tile(np.eye(4), (2, 1, 1)), [1, 1])
    with pytest.raises(ValueError, match="world_from_cam"):
        E.refine_cameras(np.zeros((2, 8, 8, 3), np.uint8), np.eye(4)[None], [1, 1])
    with pytest.raises(ValueError, match="focal_mode"):
        E.refine_cameras(np.zeros((2, 8, 8, 3), np.uint8), np.tile(np.eye(4), (2, 1, 1)), [1, 1],
                         focal_mode="true")


# ----------------------------------------------------------------------------------------------
# two-view geometry on synthetic correspondences (numpy + OpenCV)
# ----------------------------------------------------------------------------------------------

def _project(points_world, world_from_cam, K):
    cam = (np.linalg.inv(world_from_cam) @ np.c_[points_world, np.ones(len(points_world))].T)[:3].T
    uv = (K @ cam.T).T
    return (uv[:, :2] / uv[:, 2:]).astype(np.float32), cam[:, 2]


def test_relative_poses_follow_the_cam_from_cam_convention():
    rng = np.random.default_rng(9)
    H = W = 64
    K = E.intrinsics(1.0, H, W)
    truth = np.tile(np.eye(4), (4, 1, 1))
    centre = np.array([0.0, 0.0, 0.6])
    for k in range(1, 4):            # cameras on an arc around the cloud, looking at its centre
        a = 0.15 * k
        truth[k, :3, :3] = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0],
                                     [-np.sin(a), 0, np.cos(a)]])
        truth[k, :3, 3] = centre - truth[k, :3, :3] @ centre + [0, 0.02 * k, 0]
    points = rng.uniform([-0.2, -0.2, 0.45], [0.2, 0.2, 0.75], size=(600, 3))
    matches = {}
    for i in range(4):
        for j in range(i + 1, 4):
            p, zi = _project(points, truth[i], K)
            q, zj = _project(points, truth[j], K)
            ok = (zi > 0) & (zj > 0)
            matches[i, j] = (p[ok], q[ok])
    import cv2
    cv2.setRNGSeed(0)
    pp = E.relative_poses(matches, 4, K)
    assert pp.trusted[np.triu_indices(4, 1)].all() and pp.focal == pytest.approx(1.0)
    for i in range(4):
        for j in range(4):
            if i == j:
                continue
            true = np.linalg.inv(truth[j]) @ truth[i]
            got = pp.cam_from_cam[i, j]
            assert _rotation_errors_deg(got[None], true[None])[0] < 0.1
            t = true[:3, 3] / np.linalg.norm(true[:3, 3])
            assert np.degrees(np.arccos(np.clip(got[:3, 3] @ t, -1, 1))) < 1.0   # signed
    T = E.solve_cameras(pp)
    assert _rotation_errors_deg(T, truth).max() < 0.1
    s, c = _fitted_centres(T, truth)
    assert s > 0 and np.abs(c - truth[:, :3, 3]).max() < 2e-3


def test_epipolar_imports_torch_free():
    code = ("import sys; sys.modules['torch'] = None; sys.modules['scipy'] = None\n"
            "import numpy as np\n"
            "from iris_runtime import epipolar as E\n"
            "rng = np.random.default_rng(0)\n"
            "im = rng.integers(0, 256, (3, 32, 32, 3), dtype=np.uint8)\n"
            "pp = E.pairwise_poses(im, 1.0)\n"
            "T = E.solve_cameras(pp)\n"
            "assert T.shape == (3, 4, 4)\n"
            "print('ok')\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr



def test_flow_matches_leave_out_the_flat_part_of_a_photo():
    """Left half flat grey, right half texture; b is a shifted 2 px to the right. Flow in the flat
    half is unconstrained (DIS fills it with zero or its neighbours' flow, and forward and backward
    agree), so no vector may start or end there; the textured half keeps its vectors, with the
    true shift. With the test off (TEXTURE_MIN = 0) the flat half does yield vectors."""
    rng = np.random.default_rng(3)
    H, W = 32, 64
    tex = cv2.GaussianBlur(rng.integers(0, 256, (H, W + 8, 3), dtype=np.uint8), (3, 3), 0.8)
    a = np.full((H, W, 3), 128, np.uint8)
    b = a.copy()
    a[:, W // 2:] = tex[:, 4 + W // 2:4 + W]
    b[:, W // 2:] = tex[:, 2 + W // 2:2 + W]          # content moves 2 px to the right
    p, q = E.flow_matches(a, b)
    assert len(p) > 200
    # (the border of the flat half is an edge: the 3x3 window and Sobel see it from 2 px away)
    assert p[:, 0].min() >= W // 2 - 2.5 and q[:, 0].min() >= W // 2 - 2.5
    inner = (p[:, 0] > W // 2 + 4) & (p[:, 0] < W - 4)
    np.testing.assert_allclose(np.median(q[inner] - p[inner], axis=0), [2.0, 0.0], atol=0.1)
    flat_eig = cv2.cornerMinEigenVal(cv2.cvtColor(a, cv2.COLOR_RGB2GRAY), 3, ksize=3)
    assert flat_eig[:, :W // 2 - 2].max() <= E.TEXTURE_MIN < np.median(flat_eig[:, W // 2 + 2:])
    old = E.TEXTURE_MIN
    try:
        E.TEXTURE_MIN = 0.0
        p0, _ = E.flow_matches(a, b)
    finally:
        E.TEXTURE_MIN = old
    assert (p0[:, 0] < W // 2 - 4).sum() > 100

# ----------------------------------------------------------------------------------------------
# on a rendered scene (needs iris_train: torch + pyrender)
# ----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def rendered():
    pytest.importorskip("torch")
    pytest.importorskip("pyrender")
    from iris_train.synthetic import render_scene
    return render_scene(1_000_003, n_views=8, size=(64, 64))


def _canonical(world_from_cam):
    return np.linalg.inv(world_from_cam[0]) @ world_from_cam


@pytest.mark.torch
def test_global_solve_on_a_rendered_scene(rendered):
    from iris_train.metrics import relative_pose_errors, rpa
    pp = E.pairwise_poses(rendered.images)
    T = E.solve_cameras(pp)
    assert np.isfinite(T).all()
    rot, _ = relative_pose_errors(T, rendered.world_from_cam)
    assert np.median(rot) < 8.0
    assert rpa(T, rendered.world_from_cam)["rpa@30"] >= 0.7
    # Deterministic.
    np.testing.assert_array_equal(E.solve_cameras(E.pairwise_poses(rendered.images)), T)


def test_canonical_order_is_a_function_of_the_set_of_images():
    rng = np.random.default_rng(5)
    images = rng.integers(0, 256, (6, 8, 8, 3), dtype=np.uint8)
    perm = E.canonical_order(images)
    assert sorted(perm.tolist()) == list(range(6)) and perm.dtype == np.int64
    for shuffle in (rng.permutation(6) for _ in range(5)):
        np.testing.assert_array_equal(images[shuffle][E.canonical_order(images[shuffle])],
                                      images[perm])
    # Identical photos keep their given order (any order of them is the same images).
    twins = np.stack([images[0], images[1], images[0]])
    assert E.canonical_order(twins).tolist().index(0) < E.canonical_order(twins).tolist().index(2)


@pytest.mark.torch
def test_refine_cameras_does_not_depend_on_the_order_of_the_photos(rendered):
    """The same photos in another order give the same cameras, re-based on the new view 0 (the
    Seq/Rand gap of iris-eval came from the solve's order, scripts/epipolar_study.py order)."""
    refs = [0, 2, 3, 5, 7]
    model = np.tile(np.eye(4), (5, 1, 1))
    a = E.refine_cameras(rendered.images[refs], model, [1.0, 1.0], depth_range=(0.1, 1.0))
    assert a.source == "epipolar"
    for order in ([3, 0, 4, 1, 2], [4, 3, 2, 1, 0], [0, 2, 1, 4, 3]):
        b = E.refine_cameras(rendered.images[refs][order], model, [1.0, 1.0],
                             depth_range=(0.1, 1.0))
        expected = _canonical(a.world_from_cam[order])
        np.testing.assert_allclose(b.world_from_cam, expected, atol=1e-9)
        np.testing.assert_array_equal(b.focal, a.focal)
        assert b.scale == pytest.approx(a.scale, rel=1e-12)
        np.testing.assert_array_equal(b.pairwise.trusted, a.pairwise.trusted[np.ix_(order, order)])
        np.testing.assert_array_equal(b.pairwise.inliers, a.pairwise.inliers[np.ix_(order, order)])


@pytest.mark.torch
def test_locate_views_does_not_depend_on_the_order_of_the_references(rendered):
    truth = _canonical(rendered.world_from_cam)
    refs, queries = [0, 2, 3, 5, 7], [1, 4, 6]
    focal = rendered.K[0, 0] / rendered.images.shape[2]
    T, ok = E.locate_views(rendered.images[refs], truth[refs], focal, rendered.images[queries])
    shuffled = [7, 3, 0, 5, 2]
    # ... and the frame rooted at the new first reference, as a user who gives them in this
    # order sees it: the same poses in that frame.
    frame = np.linalg.inv(truth[7])
    T2, ok2 = E.locate_views(rendered.images[shuffled], frame @ truth[shuffled], focal,
                             rendered.images[queries[::-1]])
    np.testing.assert_array_equal(ok2, ok[::-1])
    assert ok.all()
    np.testing.assert_allclose(T2, frame @ T[::-1], atol=1e-6)     # LM stops at its tolerance


@pytest.mark.torch
def test_locate_views_with_the_references_fixed(rendered):
    truth = _canonical(rendered.world_from_cam)
    refs, queries = [0, 2, 3, 5, 7], [1, 4, 6]
    focal = rendered.K[0, 0] / rendered.images.shape[2]
    T, ok = E.locate_views(rendered.images[refs], truth[refs], focal, rendered.images[queries],
                           method="lines")
    assert ok.all()
    assert _rotation_errors_deg(T, truth[queries]).max() < 5.0
    baseline = np.linalg.norm(truth[refs, :3, 3] - truth[0, :3, 3], axis=1).mean()
    assert np.linalg.norm(T[:, :3, 3] - truth[queries, :3, 3], axis=1).max() < 0.35 * baseline
    # PnP on the references' triangulated pixels: as close.
    T, ok = E.locate_views(rendered.images[refs], truth[refs], focal, rendered.images[queries],
                           method="pnp")
    assert ok.all()
    assert _rotation_errors_deg(T, truth[queries]).max() < 5.0
    assert np.linalg.norm(T[:, :3, 3] - truth[queries, :3, 3], axis=1).max() < 0.35 * baseline
    with pytest.raises(ValueError, match="method"):
        E.locate_views(rendered.images[refs], truth[refs], focal, rendered.images[queries],
                       method="p3p")
    # Too few links asked for (the lines solve): unsolved, NaN.
    T, ok = E.locate_views(rendered.images[refs], truth[refs], focal, rendered.images[queries],
                           min_links=6, method="lines")
    assert not ok.any() and np.isnan(T).all()


@pytest.mark.torch
def test_runtime_epipolar_cameras_beat_the_model(rendered, model_dir):
    from iris_runtime import IrisRuntime
    from iris_train.metrics import relative_pose_errors, rpa
    rt = IrisRuntime(model_dir, threads=1)
    images = list(rendered.images)
    model = rt.encode(images)
    epi = rt.encode(images, cameras="epipolar")
    assert epi.camera_source == "epipolar" and model.camera_source == "model"
    np.testing.assert_array_equal(epi.field_maps, model.field_maps)    # the encoder's, as always
    gt = rendered.world_from_cam
    assert rpa(epi.world_from_cam, gt)["rpa@15"] > rpa(model.world_from_cam, gt)["rpa@15"]
    assert np.median(relative_pose_errors(epi.world_from_cam, gt)[0]) < 8.0
    np.testing.assert_array_equal(epi.world_from_cam[0], np.eye(4))
    # Units: the scene's median triangulated depth sits DEPTH_TARGET into the renderer's range.
    # (The solve takes the photos in canonical order: the matches and depths are that order's.)
    ce = epi.world_from_cam[:, :3, 3]
    perm = E.canonical_order(rendered.images)
    pixels = np.ascontiguousarray(rendered.images[perm])
    pp = E.pairwise_poses(pixels)
    trusted = [(i, j) for i in range(8) for j in range(i + 1, 8) if pp.trusted[i, j]]
    depths = E.match_depths(E.all_flow_matches(pixels), epi.world_from_cam[perm], epi.focal[0],
                            64, 64, trusted)
    assert np.median(depths) == pytest.approx(rt.near + E.DEPTH_TARGET * (rt.far - rt.near),
                                              rel=1e-9)
    # The grid-searched focal is the scene's, the encoder's is kept (locate checks against it).
    assert epi.focal[0] in E.FOCAL_GRID
    np.testing.assert_allclose(epi.K, epi.intrinsics())
    np.testing.assert_array_equal(epi.encoder_focal, model.focal)
    # locate on an epipolar scene: the epipolar pose with the scene's cameras fixed; a view
    # left out of the scene comes back near the camera the full solve gave it.
    left_out = epi.subset([0, 2, 3, 4, 5, 6, 7])
    T1 = rt.locate(left_out, images[1])
    assert _rotation_errors_deg(T1[None], epi.world_from_cam[1:2])[0] < 5.0
    spread = np.linalg.norm(ce, axis=1).mean()
    assert np.linalg.norm(T1[:3, 3] - ce[1]) < 0.35 * spread
    assert not np.array_equal(T1, rt.locate(model, images[1]))
    assert rt.render(epi, 2).shape == (64, 64, 3)
    sub = epi.subset([0, 3])
    assert sub.camera_source == "epipolar"
    np.testing.assert_array_equal(sub.encoder_focal, epi.encoder_focal)


@pytest.mark.torch
def test_runtime_model_cameras_are_bitwise_unchanged(rendered, model_dir):
    from iris_runtime import IrisRuntime
    rt = IrisRuntime(model_dir, threads=1)
    images = list(rendered.images[:4])
    default, model = rt.encode(images), rt.encode(images, cameras="model")
    batch = rt._load_images(images)
    maps, poses, focal = rt._run_encoder(batch, np.ones(4, bool))      # the graph's own outputs
    for scene in (default, model):
        np.testing.assert_array_equal(scene.field_maps, maps)
        np.testing.assert_array_equal(scene.world_from_cam, poses.astype(np.float64))
        np.testing.assert_array_equal(scene.focal, focal.astype(np.float64))
        assert scene.camera_source == "model" and scene.encoder_focal is None
    np.testing.assert_array_equal(rt.render(default, 1), rt.render(model, 1))


def test_bad_cameras_values_raise_typed_errors(model_dir):
    from iris_runtime import IrisRuntime
    from iris_runtime.runtime import Scene
    rt = IrisRuntime(model_dir, threads=1)
    images = [np.zeros((64, 64, 3), np.uint8)] * 2
    for bad in ("Epipolar", "colmap", 1, ["model"]):
        with pytest.raises(InputError, match="cameras"):
            rt.encode(images, cameras=bad)
    scene = rt.encode(images)
    kwargs = dict(field_maps=scene.field_maps, world_from_cam=scene.world_from_cam,
                  focal=scene.focal, K=scene.K, image_size=scene.image_size)
    with pytest.raises(InputError, match="camera_source"):
        Scene(**kwargs, camera_source="colmap")
    with pytest.raises(InputError, match="encoder_focal"):
        Scene(**kwargs, encoder_focal=[0.0, 1.0])


@pytest.mark.torch
def test_default_cameras_follow_the_manifest(rendered, model_dir, tmp_path):
    """A model trained on epipolar cameras says so in its manifest ("cameras"), and encode,
    one-shot render and iris-eval then solve the cameras by default; without the key: "model"."""
    import json
    import shutil

    from iris_runtime import IrisRuntime
    from iris_train.evaluate import _backend
    from iris_train.model import trained_cameras
    d = tmp_path / "epi"
    shutil.copytree(model_dir, d)
    doc = json.loads((d / "iris.json").read_text())
    assert doc["cameras"] == "model"                  # a random model: no training config
    doc["cameras"] = "epipolar"
    (d / "iris.json").write_text(json.dumps(doc))
    rt_model, rt_epi = IrisRuntime(model_dir, threads=1), IrisRuntime(d, threads=1)
    assert rt_model.default_cameras == "model" and rt_epi.default_cameras == "epipolar"
    images = list(rendered.images[:5])
    default, epi = rt_epi.encode(images), rt_epi.encode(images, cameras="epipolar")
    assert default.camera_source == epi.camera_source != "model"
    np.testing.assert_array_equal(default.world_from_cam, epi.world_from_cam)
    assert rt_epi.encode(images, cameras="model").camera_source == "model"
    np.testing.assert_array_equal(rt_epi.render(images, np.eye(4)), rt_epi.render(default, 0))
    backend = _backend(rt_epi)
    assert backend.default_cameras == "epipolar"
    assert backend.encode(np.stack(images), cameras="model").camera_source == "model"
    assert backend.encode(np.stack(images)).camera_source != "model"
    del doc["cameras"]                                 # manifests written before the key
    (d / "iris.json").write_text(json.dumps(doc))
    assert IrisRuntime(d, threads=1).default_cameras == "model"
    # The checkpoint side: what the training config says, "model" when it says nothing.
    assert trained_cameras({"train_config": {"render_cameras": "epipolar"}}) == "epipolar"
    assert trained_cameras({"train_config": {}}) == trained_cameras({}) == "model"


def test_cli_cameras_flag(model_dir, tmp_path):
    from PIL import Image
    rng = np.random.default_rng(0)
    paths = []
    for k in range(3):
        p = tmp_path / f"{k}.png"
        Image.fromarray(rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)).save(p)
        paths.append(str(p))
    base = [sys.executable, "-c", "import sys; sys.modules['torch'] = None; "
            "from iris_runtime.cli import main; sys.exit(main())", str(model_dir), *paths]
    out = subprocess.run(base + ["-o", str(tmp_path / "o"), "--cameras", "epipolar", "--view", "1",
                                 "--no-depth"], capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert "cameras of the inputs: " in out.stdout and (tmp_path / "o" / "view_001.png").is_file()
    bad = subprocess.run(base + ["-o", str(tmp_path / "p"), "--cameras", "sfm"],
                         capture_output=True, text=True, cwd=REPO)
    assert bad.returncode == 2 and "--cameras" in bad.stderr and len(bad.stderr.splitlines()) == 1


# ----------------------------------------------------------------------------------------------
# iris-eval --cameras epipolar (torch checkpoint backend)
# ----------------------------------------------------------------------------------------------

@pytest.mark.torch
def test_evaluate_with_epipolar_cameras_on_a_torch_model():
    torch = pytest.importorskip("torch")
    pytest.importorskip("pyrender")
    import dataclasses

    from iris_train import build_model, preset
    from iris_train.evaluate import ORDERS, _TorchBackend, evaluate
    from iris_train.synthetic import render_scene
    torch.manual_seed(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        cfg = dataclasses.replace(preset("tiny"), image_height=32, image_width=32, samples=8)
        model = build_model(cfg).eval()
        scene = render_scene(1_000_003, n_views=8, size=(32, 32))
        # One implementation: the torch backend's epipolar cameras are refine_cameras of its own.
        backend = _TorchBackend(model)
        plain = backend.encode(scene.images[:5])
        epi = backend.encode(scene.images[:5], cameras="epipolar")
        ref = E.refine_cameras(scene.images[:5], backend.poses(plain),
                               plain.focal.double().numpy(), depth_range=(cfg.near, cfg.far))
        np.testing.assert_array_equal(epi.world_from_cam.numpy(),
                                      ref.world_from_cam.astype(np.float32))
        np.testing.assert_array_equal(epi.focal.numpy(), ref.focal.astype(np.float32))
        assert backend.last_source == ref.source
        base = evaluate(model, [scene], progress=False)
        got = evaluate(model, [scene], progress=False, cameras="epipolar")
        for order in ORDERS:
            assert "cameras" not in base[order]
            c = got[order]["cameras"]
            assert c["references"] == c["targets"] == "epipolar"
            assert sum(c["sources"].values()) == 1 and 0.0 <= c["targets_epipolar"] <= 1.0
            for k in ("rpa@15", "rpa@30", "locate_rpa@30"):      # measured: 0.0 -> 0.25-0.32,
                assert got[order]["model"][k] > base[order]["model"][k]   # 0.3-0.4 -> 0.8-0.9
        with pytest.raises(ValueError, match="cameras"):
            evaluate(model, [scene], progress=False, cameras="colmap")
    finally:
        torch.set_num_threads(threads)


def test_search_focal_finds_the_true_focal_in_any_order():
    """Exact matches at fx/W = 1.3 (a grid value): every pair, whatever the order of the views,
    picks it; an unknown pair rule is refused."""
    rng = np.random.default_rng(22)
    truth = _forward_cameras(rng, 5, spread=0.3, max_angle=0.3)
    f_true = min(E.FOCAL_GRID, key=lambda f: abs(f - 1.3))
    X = np.stack([rng.uniform(-1.2, 1.2, 2000), rng.uniform(-1.2, 1.2, 2000), rng.uniform(2, 4, 2000)], 1)
    K = E.intrinsics(f_true, H_SYN, W_SYN)

    def matches_in(order):
        pix = []
        for T in truth[order]:
            Y = (X - T[:3, 3]) @ T[:3, :3]
            pix.append((Y @ K.T)[:, :2] / Y[:, 2:])
        return {(i, j): (pix[i], pix[j]) for i in range(5) for j in range(i + 1, 5)}

    for order in ([0, 1, 2, 3, 4], [3, 0, 4, 1, 2]):
        cv2.setRNGSeed(0)
        assert E.search_focal(matches_in(order), H_SYN, W_SYN) == f_true
    with pytest.raises(ValueError, match="pairs"):
        E.search_focal(matches_in([0, 1, 2, 3, 4]), H_SYN, W_SYN, pairs="near")

"""iris_runtime.cameras: each step of the camera solve against exact geometry, and the whole solve
on a ray-cast scene with true cameras (numpy + OpenCV only, torch-free).

The runtime's use of it (``IrisRuntime.encode(cameras="solve")``, ``locate``, iris-render,
iris-eval) is tested in tests/test_cameras_runtime.py."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from iris_runtime.cameras import (DEPTH_TARGET, canonical_order, locate_photos, locate_views,
                                  solve_cameras)
from iris_runtime.cameras.bundle import (_exp_so3, _write_inverse_factor, bundle_adjust,
                                         reprojection_errors)
from iris_runtime.cameras.features import (DISTINCT_DISTANCE, LOW_TEXTURE_SIZE, MIN_KEYPOINTS,
                                           MIRROR, TWIN_MIN_PIXELS, Features, distinct_keypoints,
                                           extract_features, match_features, scene_features,
                                           twin_distance)
from iris_runtime.cameras.locate import pose_distinct_first, pose_from_points
from iris_runtime.cameras.mapper import MapperOptions
from iris_runtime.cameras.tracks import build_tracks
from iris_runtime.cameras.triangulation import camera_centres, max_ray_angles, triangulate
from iris_runtime.cameras.two_view import estimate_from_distinct, estimate_two_view, intrinsics
from iris_runtime.errors import InputError

from . import np_scenes
from .tolerances import f32_tol

REPO = Path(__file__).resolve().parents[1]
SIZE = (192, 256)                                  # (H, W) of the ray-cast photos
FOCAL = 230.0                                      # their focal, pixels
DEPTH_RANGE = (0.1, 1.0)


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------

def _rotation(rng, max_angle=np.pi):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(-max_angle, max_angle)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _forward_cameras(rng, n, spread=0.4, max_angle=0.15):
    """n world_from_cam [n, 4, 4] near the origin looking down +z (view 0 = I)."""
    T = np.tile(np.eye(4), (n, 1, 1))
    for k in range(1, n):
        T[k, :3, :3] = _rotation(rng, max_angle)
        T[k, :3, 3] = spread * rng.normal(size=3)
    return T


def _cloud(rng, n=400, planar=False):
    z = np.full(n, 3.0) if planar else rng.uniform(2.0, 4.0, n)
    return np.stack([rng.uniform(-1, 1, n), rng.uniform(-0.8, 0.8, n), z], 1)


def _project(T, X, focal=FOCAL, size=SIZE):
    """Pixels [N, 2] and depths [N] of world points X in camera world_from_cam T."""
    Y = (X - T[:3, 3]) @ T[:3, :3]
    K = intrinsics(focal, size)
    return (Y @ K.T)[:, :2] / Y[:, 2:], Y[:, 2]


def _angle_deg(Ra, Rb):
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


def _pair_errors(pred, truth):
    """Max of rotation and sign-free translation-direction error (degrees), every pair."""
    out = []
    for i in range(len(truth)):
        for j in range(i + 1, len(truth)):
            a = np.linalg.inv(pred[j]) @ pred[i]
            b = np.linalg.inv(truth[j]) @ truth[i]
            ta, tb = a[:3, 3] / np.linalg.norm(a[:3, 3]), b[:3, 3] / np.linalg.norm(b[:3, 3])
            out.append(max(_angle_deg(a[:3, :3], b[:3, :3]),
                           np.degrees(np.arccos(min(1.0, abs(ta @ tb))))))
    return np.array(out)


def _rebased(T, root=0):
    return np.linalg.inv(T[root]) @ T


# ----------------------------------------------------------------------------------------------
# features
# ----------------------------------------------------------------------------------------------

def test_canonical_order_is_a_function_of_the_set_of_photos():
    rng = np.random.default_rng(5)
    images = rng.integers(0, 256, (6, 8, 8, 3), dtype=np.uint8)
    perm = canonical_order(images)
    assert sorted(perm.tolist()) == list(range(6)) and perm.dtype == np.int64
    for shuffle in (rng.permutation(6) for _ in range(5)):
        np.testing.assert_array_equal(images[shuffle][canonical_order(images[shuffle])],
                                      images[perm])
    # Identical photos keep their given order (any order of them is the same photos).
    twins = np.stack([images[0], images[1], images[0]])
    assert canonical_order(twins).tolist().index(0) < canonical_order(twins).tolist().index(2)
    with pytest.raises(InputError, match="photos"):
        canonical_order([images[0].astype(np.float32)])


def _features(desc):
    d = np.asarray(desc, np.uint8)
    return Features(np.zeros((len(d), 2)), d, (8, 8))


def test_match_features_keeps_distinct_mutual_nearest_neighbours():
    rng = np.random.default_rng(0)
    base = rng.integers(0, 60, (6, 128))
    a = base.copy()
    b = base[[3, 0, 5, 1, 2, 4]].copy()                       # a[k] is b[perm^-1 k]
    b[3] = np.clip(b[3] + rng.integers(-2, 3, 128), 0, 255)  # a little noise: still a match
    # a[4] gets two equally near copies in b (noise of the same size): the ratio test fails.
    b[5] = base[4] + rng.integers(0, 2, 128) * 4
    b = np.concatenate([b, base[[4]] + rng.integers(0, 2, (1, 128)) * 4])
    m = match_features(_features(a), _features(b))
    got = {int(i): int(j) for i, j in m}
    assert got == {0: 1, 1: 3, 2: 4, 3: 0, 5: 2}              # 4 is ambiguous (two twins)
    # Mutual: a keypoint whose nearest neighbour prefers another keypoint is not matched.
    a2 = np.stack([base[0], base[0] + 1])
    m2 = match_features(_features(a2), _features(base[:1]))
    assert m2.tolist() == []                                  # a2[0] and a2[1] both want b[0],
    #                                                           and their ratio test fails too
    assert match_features(_features(base[:1]), _features(base)).shape == (0, 2)


def test_unit_descriptors_are_computed_once_per_photo():
    rng = np.random.default_rng(1)
    f = _features(rng.integers(0, 200, (5, 128)))
    u = f.unit
    assert u.dtype == np.float32 and f.unit is u               # matched against every photo
    ref = f.descriptors / np.linalg.norm(f.descriptors.astype(np.float64), axis=1, keepdims=True)
    # Integer descriptors below 200: their squares and the sums of 128 of them (< 2^24) are exact
    # in float32, so a unit descriptor is 2 roundings (square root, division) from the float64
    # one, relative (tests/tolerances.py). A descriptor left unnormalised is off by 100x.
    np.testing.assert_allclose(u, ref, rtol=f32_tol(2))
    assert f.subset(np.array([3, 1])).unit is not u
    np.testing.assert_array_equal(f.subset(np.array([3, 1])).unit, u[[3, 1]])


def test_extract_features_is_deterministic_and_bounded():
    photo = np_scenes.render(np_scenes.cameras(1, 0.0), FOCAL, SIZE)[0]
    f1, f2 = extract_features(photo), extract_features(photo)
    np.testing.assert_array_equal(f1.uv, f2.uv)
    np.testing.assert_array_equal(f1.descriptors, f2.descriptors)
    assert len(f1) > 100 and f1.descriptors.dtype == np.uint8 and f1.image_size == SIZE
    assert (f1.uv > 0).all() and (f1.uv[:, 0] < SIZE[1]).all() and (f1.uv[:, 1] < SIZE[0]).all()
    few = extract_features(photo, max_features=50)
    np.testing.assert_array_equal(few.uv, f1.uv[:50])         # the 50 strongest, same order
    flat = extract_features(np.full((64, 64, 3), 128, np.uint8))
    assert len(flat) == 0 and flat.descriptors.shape == (0, 128)


@pytest.mark.parametrize("size", [(64, 64), SIZE])
def test_scene_features_capped_are_the_strongest_of_the_full_set(size):
    """``scene_features(max_features=m)`` (the refinement's ``MAX_KEYPOINTS``, SIFT describing
    no others) gives the first m of what it gives uncapped, found at the same enlargement: for
    photos enlarged as small photos are and for photos found as they are."""
    import cv2
    photos = [cv2.resize(p, size[::-1], interpolation=cv2.INTER_AREA)
              for p in np_scenes.render(np_scenes.cameras(2, 20.0), FOCAL, SIZE)]
    full, k = scene_features(photos, small_size=192)
    capped, k_capped = scene_features(photos, small_size=192, max_features=100)
    assert k_capped == k and min(len(f) for f in full) > 100
    for a, b in zip(full, capped):
        np.testing.assert_array_equal(b.uv, a.uv[:100])
        np.testing.assert_array_equal(b.descriptors, a.descriptors[:100])


# ----------------------------------------------------------------------------------------------
# two-view geometry
# ----------------------------------------------------------------------------------------------

def test_two_view_geometry_of_exact_matches():
    rng = np.random.default_rng(1)
    T = _forward_cameras(rng, 2, spread=0.5)
    X = _cloud(rng)
    p, _ = _project(T[0], X)
    q, _ = _project(T[1], X)
    idx = np.arange(len(X))
    g = estimate_two_view(p, q, np.stack([idx, idx], 1), FOCAL, SIZE, 1.0)
    assert g.config == "general" and len(g.inliers) == len(X)
    truth = np.linalg.inv(T[1]) @ T[0]                       # cam_1 from cam_0
    assert _angle_deg(g.cam2_from_cam1[:3, :3], truth[:3, :3]) < 1e-3
    t = truth[:3, 3] / np.linalg.norm(truth[:3, 3])
    assert np.degrees(np.arccos(min(1.0, g.cam2_from_cam1[:3, 3] @ t))) < 0.05   # with its sign
    assert g.triangulation_angle > 1.0


def test_median_triangulation_angle_against_the_geometry():
    """The median over three points of the angle between their rays from the two centres
    (computed here from the points themselves) is the middle one's; rays that meet behind the
    cameras do not count."""
    from iris_runtime.cameras.two_view import intrinsics, median_triangulation_angle
    K = intrinsics(FOCAL, SIZE)
    T = np.eye(4)
    T[0, 3] = -1.0                              # camera 2 one unit along +x: cam2 = cam1 - x
    X = np.array([[0.5, 0.2, 2.0], [0.5, -0.1, 4.0], [0.5, 0.3, 8.0]])

    def pixels(Y):
        return FOCAL * Y[:, :2] / Y[:, 2:] + K[:2, 2]

    p, q = pixels(X), pixels(X + T[:3, 3])
    got = median_triangulation_angle(p, q, T, K)
    a, b = X[1], X[1] - [1.0, 0.0, 0.0]                 # from centre 1 (origin) and centre 2
    expected = np.degrees(np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))
    assert got == pytest.approx(expected, rel=1e-9)
    # A match whose rays meet behind the cameras (swapped sides) is left out: no point counts.
    assert median_triangulation_angle(q[:1], p[:1], T, K) == 0.0


def test_twin_distance_matches_a_float64_reference():
    rng = np.random.default_rng(11)
    uv = rng.uniform(0, 100, (300, 2))
    uv[1] = uv[0] + [3.0, 4.0]                          # 5 px away: too close to count as a twin
    desc = rng.integers(0, 256, (300, 128)).astype(np.uint8)
    desc[1] = desc[0]
    desc[2] = desc[0]
    uv[2] = uv[0] + [40.0, 0.0]                         # a twin of keypoint 0, 40 px away
    got = twin_distance(Features(uv, desc, (100, 100)))
    unit = desc / np.linalg.norm(desc.astype(np.float64), axis=1, keepdims=True)
    want = np.array([min(np.linalg.norm(unit[i] - unit[j]) for j in range(len(uv))
                         if np.linalg.norm(uv[i] - uv[j]) >= TWIN_MIN_PIXELS)
                     for i in range(len(uv))])
    np.testing.assert_allclose(got, want, atol=1e-4)
    assert got[0] < 1e-3 and got[1] < 1e-3               # 0 and 2 are twins; so are 1 and 2 (37 px)
    desc[3] = desc[0][MIRROR]                           # a mirrored twin of 0, 1 and 2
    mirrored = twin_distance(Features(uv, desc, (100, 100)), mirrored=True)
    unit = desc / np.linalg.norm(desc.astype(np.float64), axis=1, keepdims=True)
    want = np.array([min(np.linalg.norm(unit[i] - unit[j][MIRROR]) for j in range(len(uv))
                         if np.linalg.norm(uv[i] - uv[j]) >= TWIN_MIN_PIXELS)
                     for i in range(len(uv))])
    np.testing.assert_allclose(mirrored, want, atol=1e-3)   # sqrt of float32 rounding near 0
    assert mirrored[[0, 1, 2, 3]].max() < 1e-3 and np.median(mirrored) > 0.3
    assert twin_distance(Features(uv[:1], desc[:1], (100, 100)))[0] == 2.0


def test_mirror_permutes_sift_descriptors_of_a_mirrored_photo():
    """SIFT's descriptor of a keypoint in a mirrored photo is the original's under ``MIRROR``;
    a photo set beside its own mirror image has mirrored twins everywhere and plain ones
    almost nowhere, and only the mirror-aware distinction sees it."""
    photo = np_scenes.render(np_scenes.cameras(1, 0.0), FOCAL, SIZE)[0]
    f, g = extract_features(photo), extract_features(np.ascontiguousarray(photo[:, ::-1]))
    mirrored_uv = np.stack([SIZE[1] - g.uv[:, 0], g.uv[:, 1]], axis=1)
    gap = np.linalg.norm(f.uv[:, None] - mirrored_uv[None], axis=2)
    same = gap.min(axis=1) < 1.0                          # the same keypoint, found mirrored
    assert same.sum() > 200
    unit = lambda d: d / np.linalg.norm(d.astype(np.float64), axis=1, keepdims=True)  # noqa: E731
    a, b = unit(f.descriptors[same]), unit(g.descriptors[gap.argmin(axis=1)[same]])
    assert np.median(np.linalg.norm(a[:, MIRROR] - b, axis=1)) < 0.05
    assert np.median(np.linalg.norm(a - b, axis=1)) > 0.4
    assert sorted(MIRROR) == list(range(128)) and (MIRROR[MIRROR] == np.arange(128)).all()

    beside = extract_features(np.ascontiguousarray(np.concatenate([photo, photo[:, ::-1]], 1)))
    assert np.median(twin_distance(beside, mirrored=True)) < 0.05
    assert distinct_keypoints(beside).mean() > 0.9
    assert (twin_distance(beside, mirrored=True) > DISTINCT_DISTANCE).mean() < 0.1


def _shifted_consensus(rng, n_right, n_shifted, shift):
    """Two cameras; ``n_right`` matches of true points and ``n_shifted`` of points matched one
    "period" ``shift`` off in the second view (a repeated texture): those agree with a camera
    moved by -shift, and outnumber the right ones."""
    T = _forward_cameras(rng, 2, spread=0.5)
    X = _cloud(rng, n_right + n_shifted)
    p, _ = _project(T[0], X)
    q, _ = _project(T[1], X + np.r_[np.zeros((n_right, 3)), np.tile(shift, (n_shifted, 1))])
    return T, X, p, q


def test_two_view_trusts_distinct_matches_over_a_shifted_consensus():
    rng = np.random.default_rng(12)
    T, _, p, q = _shifted_consensus(rng, 40, 90, np.array([0.4, 0.25, 0.0]))
    idx = np.arange(len(p))
    matches = np.stack([idx, idx], 1)
    truth = np.linalg.inv(T[1]) @ T[0]
    t = truth[:3, 3] / np.linalg.norm(truth[:3, 3])

    def t_error(g):
        return np.degrees(np.arccos(min(1.0, abs(g.cam2_from_cam1[:3, 3] @ t))))
    plain = estimate_two_view(p, q, matches, FOCAL, SIZE, 1.0)
    assert t_error(plain) > 5.0 and set(plain.inliers[:, 0]) >= set(range(40, 130))
    g = estimate_from_distinct(p, q, matches, idx < 40, FOCAL, SIZE, 1.0)
    assert g.config == "general" and t_error(g) < 0.5
    assert set(g.inliers[:, 0]) >= set(range(40))                    # the right ones, all
    assert len(g.inliers) < 60                                      # few shifted ones by chance
    assert estimate_from_distinct(p, q, matches, idx < 10, FOCAL, SIZE, 1.0) is None  # too few


def test_pose_distinct_first_trusts_distinct_points_over_a_shifted_consensus():
    rng = np.random.default_rng(13)
    T = _forward_cameras(rng, 2)
    X = _cloud(rng, 130)
    uv, _ = _project(T[1], X)
    shifted, _ = _project(T[1], X + [0.3, 0.2, 0.0])
    uv[40:] = shifted[40:]                                          # 90 points one period off
    cfw = np.linalg.inv(T[1])
    R, t, _ = pose_from_points(X, uv, FOCAL, SIZE, max_error=1.0)
    assert np.linalg.norm(t - cfw[:3, 3]) > 0.1
    R, t, inliers = pose_distinct_first(X, uv, np.arange(130) < 40, FOCAL, SIZE, max_error=1.0)
    assert _angle_deg(R, cfw[:3, :3]) < 1e-4 and np.linalg.norm(t - cfw[:3, 3]) < 1e-4
    assert inliers[:40].all() and inliers[40:].sum() < 10
    R2, t2, _ = pose_distinct_first(X, uv, np.arange(130) < 5, FOCAL, SIZE, max_error=1.0)
    np.testing.assert_allclose(t2, pose_from_points(X, uv, FOCAL, SIZE, max_error=1.0)[1])


def test_two_view_calls_a_plane_or_a_pure_rotation_planar_or_panoramic():
    rng = np.random.default_rng(2)
    T = _forward_cameras(rng, 2, spread=0.5)
    X = _cloud(rng, planar=True)
    p, _ = _project(T[0], X)
    q, _ = _project(T[1], X)
    idx = np.arange(len(X))
    assert estimate_two_view(p, q, np.stack([idx, idx], 1), FOCAL, SIZE, 1.0).config \
        == "planar_or_panoramic"
    R = T.copy()
    R[1, :3, 3] = 0.0                                        # the same centre: a rotation
    X = _cloud(rng)
    p, _ = _project(R[0], X)
    q, _ = _project(R[1], X)
    g = estimate_two_view(p, q, np.stack([idx, idx], 1), FOCAL, SIZE, 1.0)
    assert g.config == "planar_or_panoramic"
    few = estimate_two_view(p, q, np.stack([idx, idx], 1)[:10], FOCAL, SIZE, 1.0)
    assert few.config == "degenerate" and few.cam2_from_cam1 is None and len(few.inliers) == 0


# ----------------------------------------------------------------------------------------------
# tracks, triangulation, bundle adjustment, PnP
# ----------------------------------------------------------------------------------------------

def test_tracks_link_matches_across_views_and_drop_contradictions():
    feats = [Features(np.arange(2 * n, dtype=float).reshape(n, 2), np.zeros((n, 128), np.uint8),
                      (8, 8)) for n in (4, 4, 4)]
    matches = {(0, 1): np.array([[0, 1], [1, 2], [3, 3]]),
               (1, 2): np.array([[1, 0], [2, 2], [3, 0]]),      # 1:1 and 1:3 both reach 2:0
               (0, 2): np.array([[2, 3]])}
    tr = build_tracks(feats, matches)
    rows = {tuple(r) for r in tr.keypoint.tolist()}
    # 0:0-1:1-2:0-1:3-0:3 holds two keypoints of view 0 and of view 1: dropped whole.
    assert rows == {(1, 2, 2), (2, -1, 3)}
    k = tr.keypoint.tolist().index([1, 2, 2])
    np.testing.assert_array_equal(tr.uv[k], [feats[0].uv[1], feats[1].uv[2], feats[2].uv[2]])
    assert np.isnan(tr.uv[tr.keypoint[:, 1] < 0, 1]).all()


def test_triangulation_recovers_points_and_applies_its_checks():
    rng = np.random.default_rng(3)
    T = _forward_cameras(rng, 3)
    cfw = np.linalg.inv(T)
    X = _cloud(rng, 50)
    uv = np.stack([_project(Tk, X)[0] for Tk in T], 1)            # [50, 3, 2]
    use = np.ones((50, 3), bool)
    centre = np.array([SIZE[1] / 2, SIZE[0] / 2])
    Xt, ok = triangulate(cfw[:, :3, :3], cfw[:, :3, 3], FOCAL, centre, uv, use, max_error=0.5,
                         min_angle=1.0)
    assert ok.all()
    np.testing.assert_allclose(Xt, X, atol=1e-8)
    bad = uv.copy()
    bad[0, 2] += 5.0                                            # 5 px off in one view
    use1 = use.copy()
    use1[1, 1:] = False                                         # seen once
    _, ok = triangulate(cfw[:, :3, :3], cfw[:, :3, 3], FOCAL, centre, bad, use1, max_error=0.5,
                        min_angle=1.0)
    assert not ok[0] and not ok[1] and ok[2:].all()
    _, ok = triangulate(cfw[:, :3, :3], cfw[:, :3, 3], FOCAL, centre, uv, use, max_error=0.5,
                        min_angle=60.0)                         # no pair sees them that wide
    assert not ok.any()


def test_triangulation_is_track_by_track():
    """A subset of the tracks triangulates to the same bits as within the whole set (the
    refinement's rounds triangulate again only the tracks they replace), and at ``min_angle``
    0 every point passes the angle check it then skips."""
    rng = np.random.default_rng(4)
    cfw = np.linalg.inv(_forward_cameras(rng, 4))
    X = _cloud(rng, 60)
    uv = np.stack([_project(np.linalg.inv(c), X)[0] for c in cfw], 1) + rng.normal(0, 0.3,
                                                                                   (60, 4, 2))
    use = rng.random((60, 4)) < 0.7
    centre = np.array([SIZE[1] / 2, SIZE[0] / 2])
    args = (cfw[:, :3, :3], cfw[:, :3, 3], FOCAL, centre)
    X_all, ok_all = triangulate(*args, uv, use, max_error=1.0, min_angle=0.5)
    rows = np.array([41, 3, 17, 0, 59, 22])
    X_sub, ok_sub = triangulate(*args, uv[rows], use[rows], max_error=1.0, min_angle=0.5)
    np.testing.assert_array_equal(X_sub, X_all[rows])
    np.testing.assert_array_equal(ok_sub, ok_all[rows])
    X0, ok0 = triangulate(*args, uv, use, max_error=1.0, min_angle=0.0)
    err, z = reprojection_errors(*args[:2], FOCAL, centre, X0, uv)
    checked = ((use.sum(1) >= 2) & np.all(~use | ((z > 0) & (err <= 1.0)), axis=1)
               & (max_ray_angles(X0, camera_centres(*args[:2]), use) >= 0.0))
    np.testing.assert_array_equal(ok0, checked)
    assert 0 < ok0.sum() < 60


def _noisy_observations(rng, V, P, max_angle, noise, outlier_px, seen):
    """A bundle adjustment problem: V cameras (cam_from_world ``cfw [V, 4, 4]``), P points
    ``X``, their pixels ``uv [P, V, 2]`` with Gaussian ``noise`` (pixels), 3% of them moved
    ``outlier_px`` further, and ``active [P, V]`` keeping a ``seen`` share of the observations
    (all of views 0 and 1)."""
    T = _forward_cameras(rng, V, spread=0.6, max_angle=max_angle)
    X = _cloud(rng, P)
    uv = np.stack([_project(Tk, X)[0] for Tk in T], 1) + rng.normal(0, noise, (P, V, 2))
    uv[rng.random((P, V)) < 0.03] += outlier_px
    active = rng.random((P, V)) < seen
    active[:, :2] = True
    return np.linalg.inv(T), X, uv, active


def test_bundle_adjustment_recovers_cameras_focal_and_points_despite_outliers():
    rng = np.random.default_rng(4)
    T = _forward_cameras(rng, 5, spread=0.6, max_angle=0.2)
    cfw = np.linalg.inv(T)
    X = _cloud(rng, 300)
    uv = np.stack([_project(Tk, X)[0] for Tk in T], 1)
    active = rng.random((300, 5)) < 0.8
    active[:, :2] = True
    outliers = rng.random((300, 5)) < 0.03
    uv_obs = uv + np.where(outliers[..., None], rng.normal(0, 20, uv.shape), 0.0)
    R0 = np.stack([_rotation(rng, 0.02) @ R for R in cfw[:, :3, :3]])
    R0[0] = cfw[0, :3, :3]
    t0 = cfw[:, :3, 3] + np.r_[[[0, 0, 0]], 0.03 * rng.normal(size=(4, 3))]
    scale_axis = int(np.argmax(np.abs(cfw[1, :3, 3])))
    t0[1, scale_axis] = cfw[1, scale_axis, 3]                  # the scale the solve holds
    X0 = X + 0.05 * rng.normal(size=X.shape)
    centre = np.array([SIZE[1] / 2, SIZE[0] / 2])
    res = bundle_adjust(R0, t0, 1.15 * FOCAL, centre, X0, uv_obs, active, fixed_view=0,
                        scale_view=1, refine_focal=True, loss_scale=1.0, max_iterations=100)
    # (the Cauchy loss lets the 20-pixel outliers pull a little: 1e-4 of the focal)
    assert res.focal == pytest.approx(FOCAL, rel=1e-3)
    for k in range(5):
        assert _angle_deg(res.R[k], cfw[k, :3, :3]) < 0.01
    np.testing.assert_allclose(res.t, cfw[:, :3, 3], atol=1e-3)
    np.testing.assert_array_equal(res.R[0], R0[0])             # the gauge does not move
    assert res.t[1, scale_axis] == t0[1, scale_axis]
    err, _ = reprojection_errors(res.R, res.t, res.focal, centre, res.points, uv)
    assert np.median(err[active]) < 0.01
    # A fixed focal stays where it is.
    fixed = bundle_adjust(R0, t0, 1.15 * FOCAL, centre, X0, uv_obs, active, fixed_view=0,
                          scale_view=1, refine_focal=False, max_iterations=5)
    assert fixed.focal == 1.15 * FOCAL


def test_bundle_adjustment_tolerance_ends_it_at_the_first_small_step():
    """``tolerance``: the adjustment stops at the first step that lowers the cost by less than
    that share of it. A loose one runs fewer iterations and, on a well-posed problem whose
    Gauss-Newton steps shrink fast, ends within about that share of the tight one's cost, at
    the same cameras to a hundredth of a degree."""
    rng = np.random.default_rng(4)
    T = _forward_cameras(rng, 5, spread=0.6, max_angle=0.2)
    cfw = np.linalg.inv(T)
    X = _cloud(rng, 300)
    uv = np.stack([_project(Tk, X)[0] for Tk in T], 1) + rng.normal(0, 0.3, (300, 5, 2))
    active = np.ones((300, 5), bool)
    R0 = np.stack([_rotation(rng, 0.02) @ R for R in cfw[:, :3, :3]])
    R0[0] = cfw[0, :3, :3]
    t0 = cfw[:, :3, 3] + np.r_[[[0, 0, 0]], 0.03 * rng.normal(size=(4, 3))]
    X0 = X + 0.05 * rng.normal(size=X.shape)
    centre = np.array([SIZE[1] / 2, SIZE[0] / 2])
    kw = dict(fixed_view=0, scale_view=1, refine_focal=False, max_iterations=100)
    tight = bundle_adjust(R0, t0, FOCAL, centre, X0, uv, active, tolerance=1e-9, **kw)
    loose = bundle_adjust(R0, t0, FOCAL, centre, X0, uv, active, tolerance=1e-2, **kw)
    assert loose.iterations < tight.iterations < 100
    assert tight.cost <= loose.cost <= (1 + 1e-2) * tight.cost
    for k in range(5):
        assert _angle_deg(loose.R[k], tight.R[k]) < 0.01


def test_bundle_adjustment_leaves_what_nothing_observes_where_it_is():
    """Points without an observation and a view without one stay exactly where they start, and
    the rest ends as it ends without them."""
    rng = np.random.default_rng(9)
    V, P = 4, 150
    cfw, X, uv, active = _noisy_observations(rng, V, P, max_angle=0.2, noise=0.5,
                                             outlier_px=20.0, seen=0.9)
    centre = np.array([SIZE[1] / 2, SIZE[0] / 2])
    R0 = np.stack([_rotation(rng, 0.02) @ R for R in cfw[:, :3, :3]])
    R0[0] = cfw[0, :3, :3]
    t0 = cfw[:, :3, 3] + np.r_[[[0, 0, 0]], 0.02 * rng.normal(size=(V - 1, 3))]
    kw = dict(fixed_view=0, scale_view=1, refine_focal=True, loss_scale=2.0, max_iterations=30)
    ref = bundle_adjust(R0, t0, 1.05 * FOCAL, centre, X, uv, active, **kw)
    # One more view, seeing nothing, and 20 more points, seen by nobody, among the others.
    extra_R = np.concatenate([R0, _rotation(rng, 0.3)[None]])
    extra_t = np.concatenate([t0, [[0.3, -0.2, 0.1]]])
    where = np.sort(rng.choice(P + 20, 20, replace=False))
    kept = np.setdiff1d(np.arange(P + 20), where)
    X2 = np.zeros((P + 20, 3))
    X2[kept], X2[where] = X, rng.normal(size=(20, 3)) + [0, 0, 3]
    uv2 = np.zeros((P + 20, V + 1, 2))
    uv2[kept, :V] = uv
    active2 = np.zeros((P + 20, V + 1), bool)
    active2[kept, :V] = active
    res = bundle_adjust(extra_R, extra_t, 1.05 * FOCAL, centre, X2, uv2, active2, **kw)
    np.testing.assert_array_equal(res.points[where], X2[where])
    np.testing.assert_array_equal(res.R[V], extra_R[V])
    np.testing.assert_array_equal(res.t[V], extra_t[V])
    assert res.iterations == ref.iterations
    assert res.cost == pytest.approx(ref.cost, rel=1e-9)
    assert res.focal == pytest.approx(ref.focal, rel=1e-9)
    np.testing.assert_allclose(res.R[:V], ref.R, atol=1e-9)
    np.testing.assert_allclose(res.points[kept], ref.points, atol=1e-7)


def test_point_block_inverse_matches_lapack_on_stiff_blocks():
    """The adjustment's closed-form inverse of the 3x3 point blocks (Q^T Q, Q the inverse of
    the Cholesky factor) against np.linalg.inv, on blocks like a far point's (depth barely
    observed: condition numbers up to 1e10) and on round ones: relative error within what the
    condition number allows (a few eps x cond, LAPACK's own bound)."""
    rng = np.random.default_rng(3)
    axes = np.linalg.qr(rng.normal(size=(64, 3, 3)))[0]
    scales = 10.0 ** rng.uniform(-4, 6, size=(64, 3))
    scales[:8] = [[1e6, 1e6, 1e-4]] * 8                       # the stiff ones: cond 1e10
    A = np.einsum("pij,pj,pkj->pik", axes, scales, axes)
    A = 0.5 * (A + A.transpose(0, 2, 1))
    Q = np.zeros_like(A)
    _write_inverse_factor(Q.transpose(1, 2, 0), A.transpose(1, 2, 0))     # the 3x3 axes first
    ours, ref = Q.transpose(0, 2, 1) @ Q, np.linalg.inv(A)
    assert (np.triu(Q, 1) == 0).all()
    cond = np.linalg.cond(A)
    err = np.abs(ours - ref).max(axis=(1, 2)) / np.abs(ref).max(axis=(1, 2))
    assert np.isfinite(ours).all()
    assert (err <= 4 * np.finfo(float).eps * cond).all()
    identity = np.einsum("pij,pjk->pik", A.astype(np.longdouble), ours.astype(np.longdouble))
    assert np.abs(identity - np.eye(3)).max() < 1e-5


def test_bundle_adjustment_ends_where_scipy_least_squares_cannot_lower_the_cost():
    """Noisy observations (the optimum is not the truth) with outliers: from the adjusted
    cameras, points and focal, SciPy's least_squares on the same Cauchy cost and gauge finds
    nothing lower, so the Schur-complement steps reach a minimum of the right cost. The
    adjustment gets a tighter tolerance than its default: under Nielsen's damping, which falls
    at most 3 times a step, its last steps are short, and at the default tolerance it stops
    about 4e-7 of the cost above the minimum (checked last)."""
    import cv2
    from scipy.optimize import least_squares
    rng = np.random.default_rng(14)
    V, P = 4, 120
    cfw, X, uv, active = _noisy_observations(rng, V, P, max_angle=0.2, noise=0.7,
                                             outlier_px=25.0, seen=0.85)
    centre = np.array([SIZE[1] / 2, SIZE[0] / 2])
    t0 = cfw[:, :3, 3] + np.r_[[[0, 0, 0]], 0.02 * rng.normal(size=(V - 1, 3))]
    axis = int(np.argmax(np.abs(t0[1])))
    kw = dict(fixed_view=0, scale_view=1, refine_focal=True, loss_scale=2.0, max_iterations=200)
    res = bundle_adjust(cfw[:, :3, :3], t0, 1.05 * FOCAL, centre, X, uv, active, **kw,
                        tolerance=1e-8)

    free_t = np.ones((V, 3), bool)
    free_t[0] = False
    free_t[1, axis] = False

    def unpack(x):
        w, x = x[:3 * (V - 1)].reshape(V - 1, 3), x[3 * (V - 1):]
        R = np.stack([res.R[0]] + [cv2.Rodrigues(w[k])[0] @ res.R[k + 1] for k in range(V - 1)])
        t = res.t.copy()
        t[free_t], x = x[:free_t.sum()], x[free_t.sum():]
        return R, t, x[0], x[1:].reshape(P, 3)

    def residuals(x):
        R, t, f, Xp = unpack(x)
        Y = np.einsum("vij,pj->pvi", R, Xp) + t[None]
        # One residual per observation, its pixel distance: the Cauchy loss of its square is
        # the adjustment's, log(1 + |r|^2 / s^2) per observation.
        return np.linalg.norm((f * Y[..., :2] / Y[..., 2:] + centre - uv)[active], axis=1)

    # least_squares' own Jacobian ("2-point": the same steps and differences), its columns
    # differenced in 10 groups rather than one at a time: a residual (point p in view v) reads
    # view v's rotation and translation, the focal and point p, so the k-th rotation (or
    # translation) component of every view, and the k-th coordinate of every point, can move
    # together without two of them reaching one residual (scipy's grouped differences,
    # ``jac_sparsity``, would also switch its solver to LSMR; this keeps the exact one).
    pv = np.argwhere(active)                                    # (point, view) of each residual
    n_w, n_t = 3 * (V - 1), int(free_t.sum())
    view_of = np.r_[np.repeat(np.arange(1, V), 3), np.nonzero(free_t)[0], -1, np.full(3 * P, -1)]
    point_of = np.r_[np.full(n_w + n_t + 1, -1), np.repeat(np.arange(P), 3)]
    group = np.r_[np.tile(np.arange(3), V - 1), 3 + np.nonzero(free_t)[1], 6,
                  7 + np.arange(3 * P) % 3]
    reads = ((view_of[None] == pv[:, 1:]) | (point_of[None] == pv[:, :1])
             | (np.arange(view_of.size) == n_w + n_t)[None])          # [residuals, unknowns]
    assert (np.stack([reads[:, group == g].sum(1) for g in range(10)]) <= 1).all()

    def jacobian(x):
        f0 = residuals(x)
        h = np.finfo(float).eps ** 0.5 * np.where(x >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(x))
        h = (x + h) - x
        J = np.zeros((f0.size, x.size))
        for g in range(10):
            cols = group == g
            xg = x.copy()
            xg[cols] += h[cols]
            J[:, cols] = np.where(reads[:, cols], (residuals(xg) - f0)[:, None] / h[cols], 0.0)
        return J

    x0 = np.r_[np.zeros(3 * (V - 1)), res.t[free_t], res.focal, res.points.ravel()]
    ref = least_squares(residuals, x0, jac=jacobian, loss="cauchy", f_scale=2.0, method="trf",
                        xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
    assert ref.cost >= res.cost * (1 - 1e-7)
    assert res.cost == pytest.approx(ref.cost, rel=1e-7)
    R, t, f, _ = unpack(ref.x)
    assert f == pytest.approx(res.focal, rel=1e-5)
    np.testing.assert_allclose(t, res.t, atol=1e-5)
    default = bundle_adjust(cfw[:, :3, :3], t0, 1.05 * FOCAL, centre, X, uv, active, **kw)
    assert ref.cost <= default.cost <= ref.cost * (1 + 5e-7)


def _lm_reference(R0, t0, f0, X0, centre, uv, active, loss_scale, fixed_view, scale_view):
    """An independent reference for ``bundle_adjust``: SciPy's ``least_squares(method="lm")``
    (MINPACK's Levenberg-Marquardt, QR of the whole Jacobian) on the same cost, in the same free
    parameters, from the same start. Returns SciPy's result and the free parameters of a
    ``(R, t, focal, points)`` as a vector (``pack``, for comparing the two)."""
    import cv2
    from scipy.optimize import least_squares
    V, P = len(R0), len(X0)
    views = np.array([k for k in range(V) if k != fixed_view])
    free_t = np.ones((V, 3), bool)
    free_t[fixed_view] = False
    free_t[scale_view, int(np.argmax(np.abs(t0[scale_view])))] = False
    n_w, n_t = 3 * len(views), int(free_t.sum())
    s2 = float(loss_scale) ** 2

    def rotations(w):
        """exp([w]_x) [k, 3, 3], Rodrigues' formula with the series for small angles, in
        arithmetic that carries a complex step."""
        th2 = (w * w).sum(1)
        small = np.abs(th2) < 1e-8
        th = np.sqrt(np.where(small, 1.0, th2))
        a = np.where(small, 1 - th2 / 6 + th2 ** 2 / 120, np.sin(th) / th)
        b = np.where(small, 0.5 - th2 / 24 + th2 ** 2 / 720,
                     (1 - np.cos(th)) / np.where(small, 1.0, th2))
        K = np.zeros((len(w), 3, 3), w.dtype)
        K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
        K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
        return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)

    def residuals(x):
        R = R0.astype(x.dtype)
        R[views] = rotations(x[:n_w].reshape(-1, 3)) @ R0[views]     # on the left, as ours
        t = t0.astype(x.dtype)
        t[free_t] = x[n_w:n_w + n_t]
        f, Xp = x[n_w + n_t], x[n_w + n_t + 1:].reshape(P, 3)
        Y = np.einsum("vij,pj->pvi", R, Xp) + t[None]
        r = (f * Y[..., :2] / Y[..., 2:] + centre - uv)[active]                  # [n, 2]
        # "lm" takes no robust loss, so each observation's residual is scaled by g with
        # |g r|^2 = s^2 log(1 + |r|^2 / s^2): half the sum of squares is the adjustment's
        # Cauchy cost itself, and g^2 = s^2 log1p(u / s^2) / u (u = |r|^2) is smooth.
        u = (r * r).sum(1)
        g = np.sqrt(s2 * np.log1p(u / s2) / np.where(u.real > 0, u, 1.0))
        return (r * np.where(u.real > 0, g, 1.0)[:, None]).ravel()

    # The Jacobian by complex steps (Im f(x + ih) / h, h = 1e-20: no difference of two
    # rounded values, so exact to float64), its columns stepped in 10 groups: a residual (point
    # p in view v) reads view v's rotation and translation, the focal and point p, so the k-th
    # rotation (or translation) component of every view, and the k-th coordinate of every
    # point, can move together without two of them reaching one residual.
    pv = np.repeat(np.argwhere(active), 2, axis=0)             # (point, view) of each residual
    view_of = np.r_[np.repeat(views, 3), np.nonzero(free_t)[0], -1, np.full(3 * P, -1)]
    point_of = np.r_[np.full(n_w + n_t + 1, -1), np.repeat(np.arange(P), 3)]
    group = np.r_[np.tile(np.arange(3), len(views)), 3 + np.nonzero(free_t)[1], 6,
                  7 + np.arange(3 * P) % 3]
    reads = ((view_of[None] == pv[:, 1:]) | (point_of[None] == pv[:, :1])
             | (np.arange(view_of.size) == n_w + n_t)[None])          # [residuals, unknowns]
    assert (np.stack([reads[:, group == k].sum(1) for k in range(10)]) <= 1).all()

    def jacobian(x):
        J = np.zeros((len(pv), x.size))
        for k in range(10):
            cols = group == k
            xk = x.astype(complex)
            xk[cols] += 1e-20j
            J[:, cols] = np.where(reads[:, cols], residuals(xk).imag[:, None] / 1e-20, 0.0)
        return J

    def pack(R, t, f, X):
        w = [cv2.Rodrigues(R[k] @ R0[k].T)[0].ravel() for k in views]
        return np.r_[np.ravel(w), t[free_t], f, X.ravel()]

    # MINPACK's smallest tolerances: it runs to the end. The variables unscaled (x_scale 1;
    # SciPy's default for "lm" became the Jacobian's column norms in 1.16): pinned, so that the
    # reference is the same whichever SciPy runs it (on this test's problem both end alike).
    eps = np.finfo(float).eps
    ref = least_squares(residuals, pack(R0, t0, f0, X0), jac=jacobian, method="lm",
                        x_scale=1.0, ftol=eps, xtol=eps, gtol=eps, max_nfev=1000)
    return ref, pack


def test_bundle_adjustment_reaches_the_minimum_scipy_reaches_from_the_same_start():
    """``bundle_adjust`` against an independent Levenberg-Marquardt (SciPy's MINPACK, QR of the
    whole Jacobian, its own damping and scaling) on the same Cauchy cost, the same free
    parameters and the same start, several degrees and 10% of the focal off, with noise and
    outliers: both run until no step lowers the cost, and end at the same minimum (cost,
    rotations, translations, focal, points) to what float64 can tell apart."""
    rng = np.random.default_rng(0)
    V, P = 4, 100
    cfw, X, uv, active = _noisy_observations(rng, V, P, max_angle=0.25, noise=0.5,
                                             outlier_px=30.0, seen=0.85)
    R0 = np.stack([_rotation(rng, 0.06) @ R for R in cfw[:, :3, :3]])
    R0[0] = cfw[0, :3, :3]
    t0 = cfw[:, :3, 3] + np.r_[[[0, 0, 0]], 0.05 * rng.normal(size=(V - 1, 3))]
    X0 = X + 0.1 * rng.normal(size=X.shape)
    centre = np.array([SIZE[1] / 2, SIZE[0] / 2])
    # tolerance 0: it stops only where no step lowers the cost (the damping passes 1e10).
    res = bundle_adjust(R0, t0, 1.1 * FOCAL, centre, X0, uv, active, fixed_view=0, scale_view=1,
                        refine_focal=True, loss_scale=1.0, max_iterations=500, tolerance=0.0)
    ref, pack = _lm_reference(R0, t0, 1.1 * FOCAL, X0, centre, uv, active, 1.0, 0, 1)
    assert res.iterations < 500 and ref.status > 0
    # The tolerances, from float64. The cost is a sum over the n observations, each term
    # rounded to about eps of itself, so two evaluations of it (SciPy's and ours) at one point
    # differ by up to about n eps of it, and no run can tell apart points whose costs differ by
    # less: both ends are within dc = n eps cost of the minimum's cost. Around the minimum the
    # cost rises as dx^T H dx / 2 (H = J^T J at the reference's end, J the Jacobian of the
    # scaled residuals: Gauss-Newton's Hessian); the points within dc of it form an ellipsoid
    # whose half-width along parameter k is sqrt(2 dc (H^-1)_kk), so two ends differ by at most
    # twice that in each free parameter.
    eps, n = np.finfo(float).eps, int(active.sum())
    dc = n * eps * ref.cost
    assert abs(res.cost - ref.cost) <= dc
    half_width = np.sqrt(2.0 * dc * np.diag(np.linalg.inv(ref.jac.T @ ref.jac)))
    assert (np.abs(pack(res.R, res.t, res.focal, res.points) - ref.x) <= 2 * half_width).all()
    # ... which is a few degrees and pixels from where it started: a real adjustment.
    assert abs(res.focal - 1.1 * FOCAL) > 0.05 * FOCAL
    assert max(_angle_deg(res.R[k], R0[k]) for k in range(V)) > 1.0


def test_bundle_adjustment_with_nothing_observed_returns_the_start():
    rng = np.random.default_rng(21)
    cfw, X, uv, active = _noisy_observations(rng, 4, 50, max_angle=0.25, noise=0.5,
                                             outlier_px=30.0, seen=0.85)
    none = bundle_adjust(cfw[:, :3, :3], cfw[:, :3, 3], FOCAL, np.array([128.0, 96.0]), X, uv,
                         np.zeros_like(active), fixed_view=0, scale_view=1)
    assert none.iterations == 0 and none.cost == 0.0 and none.focal == FOCAL
    np.testing.assert_array_equal(none.R, cfw[:, :3, :3])
    np.testing.assert_array_equal(none.t, cfw[:, :3, 3])
    np.testing.assert_array_equal(none.points, X)


def test_bundle_adjustment_stays_finite_on_stiff_problems():
    """Stiff and extreme problems: points from 1 to 1e5 depths away (a far point's block is
    nearly singular along its ray), a view that sees a single point, a baseline of 1e-6 and
    a start whose points lie behind a camera. The result is finite, the gauge holds and the cost
    does not rise."""
    rng = np.random.default_rng(8)
    V, P = 4, 200
    T = _forward_cameras(rng, V, spread=0.5, max_angle=0.1)
    cfw = np.linalg.inv(T)
    X = _cloud(rng, P)
    X[:60, 2] = 10.0 ** rng.uniform(2, 5, 60)                    # far points
    X[:60, :2] *= X[:60, 2:] / 3.0                                # still in view
    uv = np.stack([_project(Tk, X)[0] for Tk in T], 1) + rng.normal(0, 0.3, (P, V, 2))
    active = np.ones((P, V), bool)
    active[1:, 3] = False                                         # view 3 sees one point
    centre = np.array([SIZE[1] / 2, SIZE[0] / 2])
    t0 = cfw[:, :3, 3].copy()
    tiny = t0.copy()
    tiny[1] = t0[0] + 1e-6 * (t0[1] - t0[0]) / np.linalg.norm(t0[1] - t0[0])
    behind = X.copy()
    behind[:5, 2] *= -1.0
    for t_start, X_start in ((t0, X), (tiny, X), (t0, behind)):
        res = bundle_adjust(cfw[:, :3, :3], t_start, FOCAL, centre, X_start, uv, active,
                            fixed_view=0, scale_view=1, refine_focal=True, loss_scale=1.0,
                            max_iterations=30)
        assert np.isfinite(res.R).all() and np.isfinite(res.t).all() and np.isfinite(res.focal)
        assert np.isfinite(res.points).all() and res.focal > 0
        np.testing.assert_array_equal(res.R[0], cfw[0, :3, :3])
        axis = int(np.argmax(np.abs(t_start[1])))
        assert res.t[1, axis] == t_start[1, axis]
        start = bundle_adjust(cfw[:, :3, :3], t_start, FOCAL, centre, X_start, uv, active,
                              fixed_view=0, scale_view=1, max_iterations=0)
        assert res.cost <= start.cost


def test_exp_so3_matches_opencv_rodrigues_from_zero_to_pi():
    import cv2
    rng = np.random.default_rng(5)
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.r_[0.0, 1e-12, 1e-8, 1e-4, rng.uniform(0, np.pi, 35), np.pi]
    w = axes * angles[:, None]
    ours = _exp_so3(w)
    ref = np.stack([cv2.Rodrigues(x)[0] for x in w])
    np.testing.assert_allclose(ours, ref, atol=1e-12)
    np.testing.assert_allclose(ours @ ours.transpose(0, 2, 1),
                               np.broadcast_to(np.eye(3), ours.shape), atol=1e-12)


def test_pose_from_points_is_exact_and_refuses_too_few_inliers():
    rng = np.random.default_rng(6)
    T = _forward_cameras(rng, 2)
    X = _cloud(rng, 60)
    uv, _ = _project(T[1], X)
    R, t, inliers = pose_from_points(X, uv, FOCAL, SIZE, max_error=1.0)
    assert inliers.all()
    cfw = np.linalg.inv(T[1])
    assert _angle_deg(R, cfw[:3, :3]) < 1e-6
    np.testing.assert_allclose(t, cfw[:3, 3], atol=1e-6)
    assert pose_from_points(X[:10], uv[:10], FOCAL, SIZE, max_error=1.0) is None
    junk = uv + rng.normal(0, 30, uv.shape)                      # nothing agrees
    assert pose_from_points(X, junk, FOCAL, SIZE, max_error=1.0) is None


def test_points_on_or_just_in_front_of_the_camera_are_not_inliers_and_do_not_warn():
    """Their projection divides by a zero or subnormal depth (inf or NaN; the subnormal one
    overflowed with a RuntimeWarning): such points are outliers, silently."""
    import warnings

    from iris_runtime.cameras.locate import _reprojects
    obj = np.array([[1.0, 0.0, 1e-320], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, -1.0],
                    [0.0, 0.0, 1.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        inliers = _reprojects(obj, np.zeros((5, 2)), np.eye(3), np.eye(3), np.zeros(3), 2.0)
    assert inliers.tolist() == [False, False, False, False, True]


def test_a_confident_stop_ends_the_pnp_search_as_the_full_search_ends():
    """``confident_stop``: the RANSAC runs ``confident_iterations``, after which a pose with
    ``min_inliers`` inliers would have been drawn with the RANSAC's confidence. Wherever OpenCV's
    adaptive stop ends the full search by then, the capped one returns the same pose bit for bit:
    on 60 problems from 16 to 80 correspondences, 15% to 80% of them inliers."""
    import cv2
    from iris_runtime.cameras.locate import PNP_ITERATIONS, confident_iterations
    # log(1e-4) / log(1 - (15/34)^s): 238.5 for AP3P's 4-point samples, 546.5 for 5 points.
    assert confident_iterations(34, 15, cv2.SOLVEPNP_AP3P) == 239
    assert confident_iterations(34, 15, cv2.SOLVEPNP_SQPNP) == 547
    assert confident_iterations(80, 15, cv2.SOLVEPNP_AP3P) == PNP_ITERATIONS
    assert confident_iterations(15, 15, cv2.SOLVEPNP_AP3P) == 1
    rng = np.random.default_rng(0)
    found = 0
    for _ in range(60):
        N, share = int(rng.integers(16, 81)), rng.uniform(0.15, 0.8)
        X = rng.normal(size=(N, 3)) + [0.0, 0.0, 6.0]
        uv = 100.0 * X[:, :2] / X[:, 2:] + 32.0 + rng.normal(0, 0.3, (N, 2))
        out = rng.random(N) > share
        uv[out] = rng.uniform(0, 64, (out.sum(), 2))
        full, capped = (pose_from_points(X, uv, 100.0, (64, 64), max_error=2.0,
                                         method=cv2.SOLVEPNP_AP3P, confident_stop=stop)
                        for stop in (False, True))
        assert (full is None) == (capped is None)
        if full is not None:
            found += 1
            for a, b in zip(full, capped):
                np.testing.assert_array_equal(a, b)
    assert 10 < found < 60


# ----------------------------------------------------------------------------------------------
# the whole solve on a ray-cast scene
# ----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def corner():
    """Six photos of a textured room corner on a 70-degree arc, their true cameras, the solve."""
    truth = np_scenes.cameras(6, 70.0)
    photos = np_scenes.render(truth, FOCAL, SIZE)
    return photos, truth, solve_cameras(list(photos), DEPTH_RANGE)


def test_solve_cameras_on_a_ray_cast_scene(corner):
    photos, truth, s = corner
    assert s.status == ("solved",) * 6 and s.root == 0 and s.image_size == SIZE
    np.testing.assert_array_equal(s.world_from_cam[0], np.eye(4))
    assert _pair_errors(s.world_from_cam, truth).max() < 2.0      # aliased ray-cast photos
    assert s.focal == pytest.approx(FOCAL, rel=0.02)
    np.testing.assert_allclose(s.K, intrinsics(s.focal, SIZE))
    # The unit: the median depth of the points in the cameras that see them is DEPTH_TARGET
    # of the way into the depth range.
    pm = s.point_map
    z = np.einsum("nj,nj->n", pm.points[pm.point] - s.world_from_cam[pm.view, :3, 3],
                  s.world_from_cam[pm.view, :3, 2])
    near, far = DEPTH_RANGE
    assert np.median(z) == pytest.approx(near + DEPTH_TARGET * (far - near), rel=1e-6)
    # The centres are the true ones up to that scale.
    c, ct = s.world_from_cam[:, :3, 3], _rebased(truth)[:, :3, 3]
    k = np.sum(c * ct) / np.sum(ct * ct)
    np.testing.assert_allclose(c, k * ct, atol=0.01 * np.abs(k * ct).max())


def test_solve_cameras_on_a_plane_seen_from_a_short_baseline():
    """A camera moved 24 cm in front of one textured wall: every pair is "planar_or_panoramic",
    so the mapper starts from the planar pair that moves most; every view is posed to within a
    degree and the focal found."""
    truth = np.stack([np_scenes.look_at(np.array([x, 0.0, 0.75 + 0.02 * k]),
                                        np.array([0.3 * x, 1.0, 0.75]))
                      for k, x in enumerate(np.linspace(-0.12, 0.12, 6))])
    photos = np_scenes.render(truth, 200.0, SIZE)
    feats = [extract_features(p) for p in photos]
    g = estimate_two_view(feats[0].uv, feats[5].uv, match_features(feats[0], feats[5]), 240.0,
                          SIZE, 1.0)
    assert g.config == "planar_or_panoramic"
    s = solve_cameras(list(photos), DEPTH_RANGE)
    assert s.status == ("solved",) * 6
    assert _pair_errors(s.world_from_cam, truth).max() < 1.0
    assert s.focal == pytest.approx(200.0, rel=0.05)


def test_starting_pairs_tried(corner, monkeypatch):
    """By default (``min_trials`` 2) a second start is grown at each starting focal even when
    the first registers every view, and the better reconstruction kept; ``min_trials=1`` stops
    at the first complete one. Both are as good on the corner."""
    import iris_runtime.cameras.mapper as mapper
    photos, truth, _ = corner
    grown = []
    grow = mapper._grow
    monkeypatch.setattr(mapper, "_grow", lambda rec, *a, **k: grown.append(rec.first)
                        or grow(rec, *a, **k))
    for options, starts in ((None, 2), (MapperOptions(min_trials=1), 1)):
        grown.clear()
        s = solve_cameras(list(photos), DEPTH_RANGE, options=options)
        assert s.status == ("solved",) * 6
        assert _pair_errors(s.world_from_cam, truth).max() < 2.0
        assert s.focal == pytest.approx(FOCAL, rel=0.02)
        # two reconstructions (every match; distinct keypoints first) x two starting focals
        assert len(grown) == 2 * 2 * starts


def test_a_mapping_of_too_few_views_is_left_unfinished(corner, monkeypatch):
    """``MapperOptions.finish_min_views``: a starting pair's mapping that registers fewer views
    skips its two final adjustments (the refinement's witness can use no such mapping); one
    that registers as many is finished as by default."""
    import iris_runtime.cameras.mapper as mapper
    photos = list(corner[0])
    grown = []
    grow = mapper._grow
    monkeypatch.setattr(mapper, "_grow", lambda *a, **k: grown.append(grow(*a, **k)) or grown[-1])
    first = {}
    for finish in (0, 6, 7):
        grown.clear()
        solve_cameras(photos, DEPTH_RANGE, options=MapperOptions(min_trials=1,
                                                                 finish_min_views=finish))
        first[finish] = grown[0]                   # the same inputs every time: the first map
    assert first[0].registered.all()
    for finish in (6, 7):
        np.testing.assert_array_equal(first[finish].registered, first[0].registered)
    assert first[6].history == first[0].history
    assert first[7].history == first[0].history[:-2]            # no final adjustments


def test_solve_cameras_is_deterministic_and_order_free(corner):
    photos, truth, s = corner
    order = [3, 0, 5, 1, 4, 2]
    again = solve_cameras([photos[k] for k in order], DEPTH_RANGE)
    assert again.status == ("solved",) * 6 and again.focal == pytest.approx(s.focal, rel=1e-9)
    np.testing.assert_allclose(again.world_from_cam, _rebased(s.world_from_cam[order]),
                               atol=1e-6)
    assert again.scale == pytest.approx(s.scale, rel=1e-6)


def test_solve_cameras_reports_a_photo_it_cannot_pose(corner):
    photos, _, s = corner
    import cv2
    noise = np.full(photos[0].shape, 90, np.uint8)                      # nothing in common
    for k, (x, y) in enumerate(((40, 50), (150, 60), (90, 140), (200, 120))):
        cv2.circle(noise, (x, y), 12 + 3 * k, (200, 200, 200), -1)
    out = solve_cameras([*photos[:4], noise], DEPTH_RANGE)
    assert out.status[:4] == ("solved",) * 4 and out.status[4] == "unposed"
    assert np.isnan(out.world_from_cam[4]).all() and np.isfinite(out.world_from_cam[:4]).all()
    assert out.posed.tolist() == [True] * 4 + [False]
    # View 0 unposed: the others still get cameras, rooted at the first posed view.
    first = solve_cameras([noise, *photos[:4]], DEPTH_RANGE)
    assert first.status[0] == "unposed" and first.root == 1
    np.testing.assert_array_equal(first.world_from_cam[1], np.eye(4))
    single = solve_cameras([photos[0]], DEPTH_RANGE)
    assert single.status == ("unposed",) and single.root == -1


def test_located_photos_match_the_full_solve(corner):
    photos, truth, s = corner
    part = solve_cameras([photos[k] for k in (0, 1, 2, 4, 5)], DEPTH_RANGE)
    T, ok = locate_photos(part.point_map, part.focal, part.image_size, [photos[3]])
    assert ok.all()
    full = np.concatenate([part.world_from_cam[:3], T, part.world_from_cam[3:]])
    assert _pair_errors(full, truth).max() < 1.5
    # Against known cameras (iris-eval's targets): the true ones, the true focal.
    refs = [0, 1, 2, 4, 5]
    T2, ok2 = locate_views([photos[k] for k in refs], _rebased(truth)[refs], FOCAL / SIZE[1],
                           [photos[3], photos[3][::-1].copy()])
    assert ok2.tolist() == [True, False]                       # a mirrored photo fits nowhere
    assert _angle_deg(T2[0, :3, :3], _rebased(truth)[3, :3, :3]) < 0.5
    np.testing.assert_allclose(T2[0, :3, 3], _rebased(truth)[3, :3, 3], atol=0.05)
    assert np.isnan(T2[1]).all()


def test_small_photos_are_located_as_they_were_solved(corner, monkeypatch):
    """Photos under ``MIN_SIZE`` (128x96) are solved enlarged, and a photo located against
    their points is matched at the same enlargement and contrast threshold."""
    import cv2

    import iris_runtime.cameras.locate as L
    from iris_runtime.cameras.features import SMALL_CONTRAST_THRESHOLD
    photos, truth, _ = corner
    small = [cv2.resize(p, (128, 96), interpolation=cv2.INTER_AREA) for p in photos]
    part = solve_cameras([small[k] for k in (0, 1, 2, 4, 5)], DEPTH_RANGE)
    assert part.status == ("solved",) * 5 and part.point_map.enlargement == 3
    seen = []

    def spy(photo, **kw):
        seen.append((photo.shape, kw.get("contrast_threshold")))
        return extract_features(photo, **kw)
    monkeypatch.setattr(L, "extract_features", spy)
    T, ok = locate_photos(part.point_map, part.focal, part.image_size, [small[3]])
    assert ok.all() and seen == [((288, 384, 3), SMALL_CONTRAST_THRESHOLD)]
    full = np.concatenate([part.world_from_cam[:3], T, part.world_from_cam[3:]])
    assert _pair_errors(full, truth).max() < 1.5


def test_low_texture_photos_are_solved_enlarged(corner):
    """Blurred, the corner's photos (256 wide) keep under ``MIN_KEYPOINTS`` keypoints: they are
    solved enlarged past ``LOW_TEXTURE_SIZE`` (twice), the cameras and focal still reported for
    the photos as given, and a photo located against the points is matched at the same
    enlargement."""
    import cv2
    photos, truth, _ = corner
    blurred = [cv2.GaussianBlur(p, (0, 0), 2.0) for p in photos]
    assert np.median([len(extract_features(p)) for p in blurred]) < MIN_KEYPOINTS
    feats, k = scene_features(blurred[::-1])
    assert k == 2 and max(SIZE) < LOW_TEXTURE_SIZE <= k * max(SIZE)
    assert all(f.image_size == (SIZE[0] * k, SIZE[1] * k) for f in feats)
    assert scene_features(photos)[1] == 1                        # textured: as given
    s = solve_cameras(blurred[:5], DEPTH_RANGE)
    assert s.status == ("solved",) * 5 and s.image_size == SIZE and s.point_map.enlargement == 2
    assert s.focal == pytest.approx(FOCAL, rel=0.02)
    T, ok = locate_photos(s.point_map, s.focal, s.image_size, [blurred[5]])
    assert ok.all()
    assert _pair_errors(np.concatenate([s.world_from_cam, T]), truth).max() < 2.0


def test_small_photos_are_enlarged_to_the_low_texture_size_in_one_pass(corner, monkeypatch):
    """Photos under ``MIN_SIZE`` go straight to ``LOW_TEXTURE_SIZE`` (64 -> 320: k 5, not 4
    and then 5): one SIFT pass per photo, at ``SMALL_CONTRAST_THRESHOLD``."""
    import cv2

    import iris_runtime.cameras.features as F
    photos, _, _ = corner
    small = [cv2.resize(p, (64, 48), interpolation=cv2.INTER_AREA) for p in photos[:3]]
    calls = []

    def counted(photo, **kw):
        calls.append(photo.shape)
        return extract_features(photo, **kw)
    monkeypatch.setattr(F, "extract_features", counted)
    feats, k = F.scene_features(small)
    assert k == 5 and 4 * 64 < LOW_TEXTURE_SIZE <= k * 64
    assert calls == [(240, 320, 3)] * 3 and all(f.image_size == (240, 320) for f in feats)
    # ... found at the lower contrast threshold of small photos, which keeps more of them.
    assert F.contrast_threshold((48, 64)) == F.SMALL_CONTRAST_THRESHOLD < F.CONTRAST_THRESHOLD
    assert F.contrast_threshold(SIZE) == F.CONTRAST_THRESHOLD
    at_default = extract_features(F.enlarge(small[0], 5))
    np.testing.assert_array_equal(
        feats[0].uv, extract_features(F.enlarge(small[0], 5),
                                      contrast_threshold=F.SMALL_CONTRAST_THRESHOLD).uv)
    assert len(feats[0]) > len(at_default)
    # The refinement's smaller enlargement: to MIN_SIZE (k 4), one pass.
    calls.clear()
    feats, k = F.scene_features(small, small_size=F.MIN_SIZE)
    assert k == 4 and calls == [(192, 256, 3)] * 3 and feats[0].image_size == (192, 256)


# ----------------------------------------------------------------------------------------------
# refining a model's cameras
# ----------------------------------------------------------------------------------------------

def _perturbed(truth, rng, degrees=6.0, shift=0.15, unit=3.0):
    """``truth`` re-based on view 0, in another unit, each view but 0 turned by ``degrees``
    about a random axis and its centre moved by ``shift`` of the largest baseline: what a camera
    head several degrees off gives."""
    start = _rebased(truth).copy()
    start[:, :3, 3] *= unit
    reach = np.linalg.norm(start[:, :3, 3], axis=1).max()
    for k in range(1, len(start)):
        axis = rng.normal(size=3)
        start[k, :3, :3] = _rotation_about(axis, np.radians(degrees)) @ start[k, :3, :3]
        start[k, :3, 3] += shift * reach * rng.normal(size=3) / np.sqrt(3)
    return start


def _rotation_about(axis, angle):
    import cv2
    return cv2.Rodrigues(np.asarray(axis, np.float64) / np.linalg.norm(axis) * angle)[0]


def test_refine_cameras_recovers_the_solve_from_a_start_degrees_off(corner):
    """From cameras 6 degrees and 15% of the baseline off and a focal 15% off, the refinement
    lands where the full solve does (its reference here): every pair within a degree of it and
    within 2 of the truth, the focal within 2%, in the solve's unit (median point depth at
    ``DEPTH_TARGET``)."""
    from iris_runtime.cameras import refine_cameras
    photos, truth, solved = corner
    start = _perturbed(truth, np.random.default_rng(3))
    assert _pair_errors(start, truth).max() > 6.0
    s = refine_cameras(list(photos), start, 1.15 * FOCAL, DEPTH_RANGE)
    assert s.status == ("solved",) * 6 and s.root == 0 and s.image_size == SIZE
    np.testing.assert_array_equal(s.world_from_cam[0], np.eye(4))
    assert _pair_errors(s.world_from_cam, solved.world_from_cam).max() < 1.0
    assert _pair_errors(s.world_from_cam, truth).max() < 2.0
    assert s.focal == pytest.approx(FOCAL, rel=0.02)
    pm = s.point_map
    z = np.einsum("nj,nj->n", pm.points[pm.point] - s.world_from_cam[pm.view, :3, 3],
                  s.world_from_cam[pm.view, :3, 2])
    near, far = DEPTH_RANGE
    assert np.median(z) == pytest.approx(near + DEPTH_TARGET * (far - near), rel=1e-6)
    # Its points locate a photo left out, as the solve's do.
    part = refine_cameras([photos[k] for k in (0, 1, 2, 4, 5)], start[[0, 1, 2, 4, 5]],
                          FOCAL, DEPTH_RANGE)
    T, ok = locate_photos(part.point_map, part.focal, part.image_size, [photos[3]])
    assert ok.all()
    full = np.concatenate([part.world_from_cam[:3], T, part.world_from_cam[3:]])
    assert _pair_errors(full, truth).max() < 2.0


def test_refine_cameras_is_order_free(corner):
    """As the solve: the same photos and start in another order give the same cameras, re-based
    on the new view 0 (the refinement runs in ``canonical_order``)."""
    from iris_runtime.cameras import refine_cameras
    photos, truth, _ = corner
    start = _perturbed(truth, np.random.default_rng(3))
    s = refine_cameras(list(photos), start, FOCAL, DEPTH_RANGE)
    order = [3, 0, 5, 1, 4, 2]
    again = refine_cameras([photos[k] for k in order], _rebased(start[order]), FOCAL,
                           DEPTH_RANGE)
    assert again.status == ("solved",) * 6 and again.focal == pytest.approx(s.focal, rel=1e-6)
    np.testing.assert_allclose(again.world_from_cam, _rebased(s.world_from_cam[order]),
                               atol=1e-6)


def test_refine_cameras_starts_from_the_pairs_where_the_model_is_far_off(corner):
    """A start 40 degrees off (a head that has not learned the scene) cannot be adjusted into
    place; with the pairs' averaged rotations (and the start's centres, 15% of a baseline off) it
    can, and that adjustment is kept."""
    import iris_runtime.cameras.refine as refine
    photos, truth, _ = corner
    start = _perturbed(truth, np.random.default_rng(5), degrees=40.0, shift=0.15)
    s = refine.refine_cameras(list(photos), start, FOCAL, DEPTH_RANGE)
    assert s.status == ("solved",) * 6
    assert _pair_errors(s.world_from_cam, truth).max() < 2.0
    model_only = refine.RefineOptions(starts=refine.StartOptions(kinds=("model",)))
    alone = refine.refine_cameras(list(photos), start, FOCAL, DEPTH_RANGE, refinement=model_only)
    assert alone is None or _pair_errors(alone.world_from_cam, truth).max() > 10.0


def _relative_poses(T, pairs):
    """{(a, b): (cam_b_from_cam_a [4, 4] with a unit translation, weight 1)} of world_from_cam T."""
    out = {}
    for a, b in pairs:
        rel = np.linalg.inv(T[b]) @ T[a]
        rel[:3, 3] /= np.linalg.norm(rel[:3, 3])
        out[a, b] = (rel, 1.0)
    return out


def test_rotation_and_centre_averaging_recover_the_cameras_despite_a_wrong_pair():
    """Exact relative poses of 6 cameras on every pair, one pair's rotation turned 30 degrees:
    the averaged rotations are the true ones to 0.5 degree (the wrong pair reweighted away; 4.9
    degrees without the reweighting), exact without it; a view no pair links keeps its start.
    The centres from the exact baseline directions are the true ones in the start's scale."""
    from iris_runtime.cameras.refine import average_centres, average_rotations
    rng = np.random.default_rng(8)
    truth = _forward_cameras(rng, 6, spread=0.4, max_angle=0.4)
    pairs = [(a, b) for a in range(6) for b in range(a + 1, 6)]
    rel = _relative_poses(truth, pairs)
    cam_from_world = np.linalg.inv(truth)
    R_true = cam_from_world[:, :3, :3]
    R_start = np.stack([_rotation_about(rng.normal(size=3), 0.3) @ R for R in R_true])
    R_start[0] = R_true[0]
    rotations = {ab: (T[:3, :3], w) for ab, (T, w) in rel.items()}       # cam_b_from_cam_a
    exact = average_rotations(rotations, R_start)
    assert max(_angle_deg(a, b) for a, b in zip(exact, R_true)) < 1e-4      # arccos rounding
    bad = dict(rotations)
    bad[1, 3] = (_rotation_about([0.0, 1.0, 0.2], np.radians(30)) @ rotations[1, 3][0], 1.0)
    robust = average_rotations(bad, R_start)
    assert max(_angle_deg(a, b) for a, b in zip(robust, R_true)) < 0.5
    start_centres = 2.0 * truth[:, :3, 3] + 0.05 * rng.normal(size=(6, 3))
    centres = average_centres(rel, R_true, start_centres)
    np.testing.assert_allclose(centres[0], start_centres[0])
    k = np.sum((centres - centres[0]) * (truth[:, :3, 3] - truth[0, :3, 3])) \
        / np.sum((truth[:, :3, 3] - truth[0, :3, 3]) ** 2)
    assert k == pytest.approx(2.0, rel=0.1)
    np.testing.assert_allclose(centres - centres[0], k * (truth[:, :3, 3] - truth[0, :3, 3]),
                               atol=1e-9)
    linked = average_rotations({ab: r for ab, r in rotations.items() if 5 not in ab}, R_start)
    np.testing.assert_array_equal(linked[5], R_start[5])
    assert max(_angle_deg(a, b) for a, b in zip(linked[:5], R_true[:5])) < 1e-4


def test_agreement_counts_the_pairs_two_sets_of_cameras_agree_on():
    """The same 6 cameras in another frame and unit agree on every pair; one turned by 10
    degrees, one moved sideways by a third of its baseline, or one the second set leaves unposed,
    on the 10 of the 15 pairs without it; at 4 degrees (under ``AgreementOptions.degrees``) on all of
    them. Pairs the first set leaves unposed do not count. A mirrored path (baselines reversed)
    agrees on none."""
    from iris_runtime.cameras.refine import agreement
    rng = np.random.default_rng(12)
    truth = _forward_cameras(rng, 6, spread=0.4, max_angle=0.4)
    cam_from_world = np.linalg.inv(truth)
    R, t = cam_from_world[:, :3, :3], cam_from_world[:, :3, 3]
    posed = np.ones(6, bool)
    similar = np.eye(4)
    similar[:3, :3] = _rotation_about([1.0, 2.0, 0.5], 1.0)
    similar[:3, 3] = [3.0, -1.0, 2.0]
    other = truth.copy()
    other[:, :3, 3] *= 2.5                                      # another unit ...
    other = similar @ other                                     # ... and frame
    c = np.linalg.inv(other)
    assert agreement(R, t, posed, c[:, :3, :3], c[:, :3, 3], posed) == pytest.approx(1.0)

    def changed(view, degrees=0.0, shift=0.0):
        T = truth.copy()
        T[view, :3, :3] = _rotation_about([0.2, 1.0, 0.3], np.radians(degrees)) @ T[view, :3, :3]
        baseline = np.linalg.norm(T[view, :3, 3] - T[0, :3, 3])
        T[view, :3, 3] += shift * baseline * T[view, :3, 0]     # along the camera's x axis
        c = np.linalg.inv(T)
        return c[:, :3, :3], c[:, :3, 3]

    assert agreement(R, t, posed, *changed(2, degrees=10.0), posed) == pytest.approx(10 / 15)
    assert agreement(R, t, posed, *changed(2, degrees=4.0), posed) == pytest.approx(1.0)
    assert agreement(R, t, posed, *changed(3, shift=1 / 3), posed) == pytest.approx(10 / 15)
    unposed = posed.copy()
    unposed[4] = False
    assert agreement(R, t, posed, R, t, unposed) == pytest.approx(10 / 15)
    assert agreement(R, t, unposed, R, t, posed) == 1.0      # only the pairs a poses count
    mirrored = truth.copy()
    mirrored[:, :3, 3] = 2 * truth[0, :3, 3] - truth[:, :3, 3]
    c = np.linalg.inv(mirrored)
    assert agreement(R, t, posed, c[:, :3, :3], c[:, :3, 3], posed) == 0.0


def test_refine_cameras_falls_back_where_no_other_start_agrees(corner):
    """The gate on ``AgreementOptions.min_share``: a refinement whose starts end at the same
    cameras is kept; held to an agreement no start reaches, and with no set of views large
    enough to salvage (``SalvageOptions.min_core_share``), it gives None, and
    ``refine_model_cameras`` the solve. With one start the check is off."""
    import iris_runtime.cameras.refine as refine
    from iris_runtime.cameras import refine_model_cameras
    photos, truth, solved = corner
    start = _perturbed(truth, np.random.default_rng(4), degrees=6.0)
    kept = refine.refine_cameras(list(photos), start, FOCAL, DEPTH_RANGE)
    assert kept is not None and _pair_errors(kept.world_from_cam, truth).max() < 2.0
    unreachable = refine.RefineOptions(agreement=refine.AgreementOptions(min_share=1.01),
                                       salvage=refine.SalvageOptions(min_core_share=1.01))
    assert refine.refine_cameras(list(photos), start, FOCAL, DEPTH_RANGE,
                                 refinement=unreachable) is None
    H, W = SIZE
    cams = refine_model_cameras(list(photos), start, [FOCAL / W, FOCAL / H], SIZE, DEPTH_RANGE,
                                refinement=unreachable)
    assert cams.source == "solve"
    np.testing.assert_array_equal(cams.world_from_cam, solved.world_from_cam)
    model_only = refine.RefineOptions(starts=refine.StartOptions(kinds=("model",)),
                                      agreement=unreachable.agreement,
                                      salvage=unreachable.salvage)
    alone = refine.refine_cameras(list(photos), start, FOCAL, DEPTH_RANGE, refinement=model_only)
    assert alone is not None and _pair_errors(alone.world_from_cam, truth).max() < 2.0


@pytest.mark.parametrize("core_share", [0.5, 5 / 6, 1.0])
def test_refine_cameras_salvages_the_views_two_starts_agree_on(corner, monkeypatch, core_share):
    """Where no start confirms the best, the views another start agrees with it on are kept and
    the others posed against their points: with view 2 made to disagree and every start's pose
    of it turned 30 degrees, the salvage still ends at the true cameras (view 2 re-posed by PnP,
    not kept); with a core share above the 5 of 6 views that agree, the scene goes to the solve.
    """
    import iris_runtime.cameras.refine as refine
    from iris_runtime.cameras.refine import confirm, salvage
    photos, truth, _ = corner
    start = _perturbed(truth, np.random.default_rng(4), degrees=6.0)
    pairs, salvaged = confirm.agreeing_pairs, salvage.salvage_agreed_views

    def view_2_disagrees(*args):
        agree = pairs(*args)
        agree[2, :] = agree[:, 2] = False
        return agree

    def turned(best, witnesses, *args):
        for rec in (best, *witnesses):
            rec.R[2] = _rotation_about([0.3, 1.0, 0.1], np.radians(30.0)) @ rec.R[2]
        return salvaged(best, witnesses, *args)

    monkeypatch.setattr(confirm, "agreeing_pairs", view_2_disagrees)
    monkeypatch.setattr(salvage, "salvage_agreed_views", turned)
    stages = refine.RefineOptions(agreement=refine.AgreementOptions(min_share=1.01),
                                  salvage=refine.SalvageOptions(min_core_share=core_share))
    out = refine.refine_cameras(list(photos), start, FOCAL, DEPTH_RANGE, refinement=stages)
    if core_share > 5 / 6:
        assert out is None
        return
    assert out.status == ("solved",) * 6
    assert _pair_errors(out.world_from_cam, truth).max() < 2.0


@pytest.mark.parametrize("witness", ["confirms", "salvages", "off"])
def test_refine_cameras_asks_a_mapping_where_no_start_agrees_on_enough_views(corner, monkeypatch,
                                                                             witness):
    """Where no start confirms the best and none agrees with it on enough views to salvage, the
    incremental mapper's own reconstruction of the refinement's pairs (``witness_mapping``) is
    asked. It owes nothing to the starts: on the corner it poses all six views at the true
    cameras. A start it confirms is kept; where it confirms none, the views it agrees with the
    best on are salvaged; with ``WitnessOptions.trials = 0`` there is no witness and the caller
    runs the solve.
    """
    import iris_runtime.cameras.refine as refine
    from iris_runtime.cameras.refine import confirm
    from iris_runtime.cameras.refine import salvage as salvage_stage
    from iris_runtime.cameras.refine import witness as witness_stage
    photos, truth, _ = corner
    start = _perturbed(truth, np.random.default_rng(4), degrees=6.0)
    agreement, mapping = confirm.agreement, witness_stage.witness_mapping
    core, salvage = salvage_stage.salvage_core, salvage_stage.salvage_agreed_views
    mapped, salvages = [], []

    def counted(best, witnesses, *args):
        salvages.append(witnesses)
        return salvage(best, witnesses, *args)

    def recorded(*args):
        mapped.append(mapping(*args))
        return mapped[-1]

    def only_the_witness(R_a, t_a, posed_a, R_b, t_b, posed_b, *degrees):
        asked = witness == "confirms" and mapped and any(R is mapped[-1].R for R in (R_a, R_b))
        return agreement(R_a, t_a, posed_a, R_b, t_b, posed_b, *degrees) if asked else 0.0

    def no_start_core(best, witnesses, *options):
        return core(best, witnesses, *options) if mapped and witnesses == [mapped[-1]] else None

    monkeypatch.setattr(witness_stage, "witness_mapping", recorded)
    monkeypatch.setattr(salvage_stage, "salvage_agreed_views", counted)
    monkeypatch.setattr(confirm, "agreement", only_the_witness)
    monkeypatch.setattr(salvage_stage, "salvage_core", no_start_core)
    stages = refine.RefineOptions(
        witness=refine.WitnessOptions(trials=0 if witness == "off" else 2))
    out = refine.refine_cameras(list(photos), start, FOCAL, DEPTH_RANGE, refinement=stages)
    if witness == "off":
        assert out is None and not mapped
        return
    assert len(mapped) == 1 and mapped[0].registered.all()
    # The starts' salvage, then (where the witness confirms no start) the witness's.
    assert len(salvages) == (1 if witness == "confirms" else 2)
    # The witness in the photos' order (the refinement works in canonical_order).
    from iris_runtime.cameras.features import canonical_order
    perm = canonical_order(list(photos))
    cam_from_world = np.tile(np.eye(4), (6, 1, 1))
    cam_from_world[perm, :3, :3], cam_from_world[perm, :3, 3] = mapped[0].R, mapped[0].t
    assert _pair_errors(np.linalg.inv(cam_from_world), truth).max() < 2.0
    assert out.status == ("solved",) * 6
    assert _pair_errors(out.world_from_cam, truth).max() < 2.0


def test_the_solve_and_the_refinement_adjust_with_bundle_adjust(corner, monkeypatch):
    """One adjuster: the solve's mapper, the refinement's rounds and its witness mapping all
    adjust with ``bundle.bundle_adjust``, the solve for ``MapperOptions.ba_iterations`` and
    ``final_ba_iterations``, the witness for ``WitnessOptions.iterations``."""
    import iris_runtime.cameras.bundle as bundle
    import iris_runtime.cameras.mapper as mapper
    import iris_runtime.cameras.refine as refine
    from iris_runtime.cameras.refine import confirm, rounds, salvage, witness
    photos, truth, _ = corner
    calls = {mapper: 0, rounds: 0}
    mapper_iterations = set()

    def counting(module):
        def counted(*args, **kw):
            calls[module] += 1
            if module is mapper:
                mapper_iterations.add(kw["max_iterations"])
            return bundle.bundle_adjust(*args, **kw)
        return counted

    for module in calls:
        assert module.bundle_adjust is bundle.bundle_adjust
        monkeypatch.setattr(module, "bundle_adjust", counting(module))
    solve_cameras(list(photos), DEPTH_RANGE)
    assert calls[mapper] > 0 and calls[rounds] == 0
    solve_options = MapperOptions()
    assert mapper_iterations == {solve_options.ba_iterations, solve_options.final_ba_iterations}
    calls.update({mapper: 0})
    mapper_iterations.clear()
    # No start agrees and none salvages: the rounds, then the witness, run.
    witnessed = []
    mapping = witness.witness_mapping
    monkeypatch.setattr(confirm, "agreement", lambda *args: 0.0)
    monkeypatch.setattr(salvage, "salvage_core", lambda *args: None)
    monkeypatch.setattr(witness, "witness_mapping",
                        lambda *args: witnessed.append(1) or mapping(*args))
    refine.refine_cameras(list(photos), _perturbed(truth, np.random.default_rng(4), 6.0), FOCAL,
                          DEPTH_RANGE)
    assert witnessed and calls[rounds] > 0 and calls[mapper] > 0
    assert mapper_iterations == set(refine.WitnessOptions().iterations)


def test_the_salvage_and_the_witness_cap_their_pnp_ransac(corner, monkeypatch):
    """The solve's registrations run ``PNP_ITERATIONS``; the refinement's salvage and witness at
    most ``CappedPnP.max_iterations`` (and fewer where ``confident_iterations`` says so)."""
    import cv2

    import iris_runtime.cameras.locate as locate
    import iris_runtime.cameras.refine as refine
    from iris_runtime.cameras.refine import confirm, salvage
    photos, truth, _ = corner
    counts = []
    ransac = cv2.solvePnPRansac

    def recorded(*args, iterationsCount, **kw):
        counts.append(iterationsCount)
        return ransac(*args, iterationsCount=iterationsCount, **kw)

    monkeypatch.setattr(locate.cv2, "solvePnPRansac", recorded)
    solve_cameras(list(photos), DEPTH_RANGE)
    assert max(counts) == locate.PNP_ITERATIONS
    counts.clear()
    # No start agrees: the salvage (its core from the witness alone) and the witness run.
    core = salvage.salvage_core
    monkeypatch.setattr(confirm, "agreement", lambda *args: 0.0)
    monkeypatch.setattr(salvage, "salvage_core",
                        lambda best, witnesses, *options: core(best, witnesses, *options)
                        if len(witnesses) == 1 and witnesses[0].history else None)
    refine.refine_cameras(list(photos), _perturbed(truth, np.random.default_rng(4), 6.0), FOCAL,
                          DEPTH_RANGE)
    pnp = refine.CappedPnP()
    assert counts and max(counts) <= pnp.max_iterations < locate.PNP_ITERATIONS
    # By the cap, a pose that 42% of the correspondences support would have been drawn with the
    # RANSAC's confidence; one that 41% support not yet (the cap's reason, CappedPnP's doc).
    assert (locate.confident_iterations(100, 42, pnp.method)
            <= pnp.max_iterations
            < locate.confident_iterations(100, 41, pnp.method))

def test_refine_cameras_ranks_its_starts_in_the_photos_pixels(corner, monkeypatch):
    """The starts are ranked as the mapper ranks reconstructions (``reprojection_score``), with
    its truncation in the photos' pixels as the solve has it: 3 px at 320 px, 4.8 px on photos
    of 512 px (the corner enlarged twice), not the reference size's 3."""
    import iris_runtime.cameras.refine as refine
    from iris_runtime.cameras.refine import starts
    from iris_runtime.cameras.two_view import pixel_scale
    photos, truth, _ = corner
    large = [np.repeat(np.repeat(p, 2, axis=0), 2, axis=1) for p in photos]
    score, seen = starts.reprojection_score, []

    def recorded(rec, tracks, centre, opts):
        seen.append(opts.max_error)
        return score(rec, tracks, centre, opts)

    monkeypatch.setattr(starts, "reprojection_score", recorded)
    start = _perturbed(truth, np.random.default_rng(4), degrees=6.0)
    out = refine.refine_cameras(large, start, 2 * FOCAL, DEPTH_RANGE)
    assert out is not None and _pair_errors(out.world_from_cam, truth).max() < 2.0
    expected = MapperOptions().max_error * pixel_scale(large[0].shape[:2])
    assert expected == pytest.approx(4.8) and seen == [expected] * len(seen) and seen


def test_the_witness_confirms_a_start_only_on_the_views_both_pose(monkeypatch):
    """``witness_verdict`` takes a start the witness agrees with both ways: a start at the true
    cameras that leaves view 1 unposed is not confirmed by a witness that poses all five views
    (on one real set that start left a view with the head's camera), the same start posing every
    view is; with no start confirmed it salvages ``best`` (here: nothing to salvage, None)."""
    import iris_runtime.cameras.refine as refine
    from iris_runtime.cameras.mapper import Reconstruction
    from iris_runtime.cameras.refine import salvage
    from iris_runtime.cameras.refine import witness as witness_stage
    truth = np_scenes.cameras(5, 70.0)
    cam = np.linalg.inv(truth)

    def rec(registered, turned=()):
        R = cam[:, :3, :3].copy()
        for v in turned:
            R[v] = _rotation_about([0.3, 1.0, 0.1], np.radians(20.0)) @ R[v]
        return Reconstruction(R, cam[:, :3, 3].copy(), FOCAL, np.array(registered),
                              np.zeros((0, 3)), np.zeros(0, bool), np.zeros((0, 5), bool), (0, 1))

    monkeypatch.setattr(salvage, "salvage_agreed_views", lambda best, witnesses, *args: None)
    witness = rec([True] * 5)
    best = rec([True] * 5, turned=(2, 3))                 # right on the pairs of 0, 1 and 4 only
    partial = rec([True, False, True, True, True])        # right, but view 1 unposed
    assert refine.agreement(partial.R, partial.t, partial.registered, witness.R, witness.t,
                            witness.registered) == 1.0  # one way it agrees on every pair
    verdict = witness_stage.witness_verdict
    assert verdict(best, [partial], witness, None, None) is None
    full = rec([True] * 5)
    assert verdict(best, [partial, full], witness, None, None) is full
    assert verdict(best, [full], None, None, None) is None


def test_agreeing_views_is_the_largest_set_that_agrees_pair_by_pair():
    """A largest clique of the agreement graph, the lowest views among equals; no two views
    agree: none."""
    from iris_runtime.cameras.refine import agreeing_views
    agree = np.zeros((6, 6), bool)
    for i, j in [(0, 1), (0, 2), (1, 2), (2, 3), (3, 4), (4, 5), (3, 5), (2, 4), (2, 5)]:
        agree[i, j] = agree[j, i] = True
    np.testing.assert_array_equal(agreeing_views(agree), [0, 0, 1, 1, 1, 1])    # {2, 3, 4, 5}
    agree[2, 5] = agree[5, 2] = False                     # now {0, 1, 2}, {2, 3, 4}, {3, 4, 5}
    np.testing.assert_array_equal(agreeing_views(agree), [1, 1, 1, 0, 0, 0])
    np.testing.assert_array_equal(agreeing_views(np.zeros((4, 4), bool)), [0, 0, 0, 0])


def test_refine_cameras_reports_what_the_photos_cannot_constrain(corner):
    """A photo that matches nothing is "unposed" (NaN); a start without a baseline, or photos
    that share nothing, give None, and ``refine_model_cameras`` then falls back to the solve."""
    import cv2

    from iris_runtime.cameras import refine_cameras, refine_model_cameras
    photos, truth, solved = corner
    start = _perturbed(truth, np.random.default_rng(4), degrees=3.0)
    noise = np.full(photos[0].shape, 90, np.uint8)
    for k, (x, y) in enumerate(((40, 50), (150, 60), (90, 140), (200, 120))):
        cv2.circle(noise, (x, y), 12 + 3 * k, (200, 200, 200), -1)
    out = refine_cameras([*photos[:4], noise], start[:5], FOCAL, DEPTH_RANGE)
    assert out.status == ("solved",) * 4 + ("unposed",)
    assert np.isnan(out.world_from_cam[4]).all() and np.isfinite(out.world_from_cam[:4]).all()
    assert _pair_errors(out.world_from_cam[:4], truth[:4]).max() < 2.0
    collapsed = start.copy()
    collapsed[:, :3, 3] = 0.0
    assert refine_cameras(list(photos), collapsed, FOCAL, DEPTH_RANGE) is None
    assert refine_cameras([noise, noise[::-1].copy()], start[:2], FOCAL, DEPTH_RANGE) is None
    # At the model's resolution: the fallback is the solve itself, bit for bit.
    H, W = SIZE
    cams = refine_model_cameras(list(photos), collapsed, [FOCAL / W, FOCAL / H], SIZE,
                                DEPTH_RANGE)
    assert cams.source == "solve"
    np.testing.assert_array_equal(cams.world_from_cam, solved.world_from_cam)
    refined = refine_model_cameras(list(photos), start, [FOCAL / W, FOCAL / H], SIZE,
                                   DEPTH_RANGE)
    assert refined.source == "refined" and refined.status == ("solved",) * 6
    assert refined.focal[0] == pytest.approx(FOCAL / W, rel=0.02)


def test_refine_cameras_refuses_bad_input(corner):
    from iris_runtime.cameras import refine_cameras
    photos, truth, _ = corner
    start = _rebased(truth)
    sheared = start.copy()
    sheared[1, :3, :3] *= 1.1
    bottom = start.copy()
    bottom[2, 3, 0] = 0.5
    nan = start.copy()
    nan[3, 0, 3] = np.nan
    for bad, match in ((start[:5], r"world_from_cam.*\[6, 4, 4\]"),
                       (start[:, :3], r"world_from_cam.*\[6, 4, 4\]"),
                       (nan, "world_from_cam: expected finite"),
                       (sheared, r"world_from_cam\[1\]: expected a rigid"),
                       (bottom, r"world_from_cam\[2\]: expected a rigid")):
        with pytest.raises(InputError, match=match):
            refine_cameras(list(photos), bad, FOCAL, DEPTH_RANGE)
    for focal in (0.0, -5.0, np.nan, np.inf, [FOCAL, FOCAL], "230"):
        with pytest.raises(InputError, match="focal"):
            refine_cameras(list(photos), start, focal, DEPTH_RANGE)
    with pytest.raises(InputError, match="depth_range"):
        refine_cameras(list(photos), start, FOCAL, (1.0, 0.1))
    with pytest.raises(InputError, match=r"photos\[1\]"):
        refine_cameras([photos[0], photos[1][:, :100]], start[:2], FOCAL, DEPTH_RANGE)


def test_solve_cameras_refuses_bad_input():
    good = [np.zeros((32, 32, 3), np.uint8)] * 2
    for bad, match in (([], "photos"), ([np.zeros((32, 32, 3), np.float32)], r"photos\[0\]"),
                       ([np.zeros((32, 32, 3), np.uint8), np.zeros((32, 40, 3), np.uint8)],
                        r"photos\[1\]"),
                       ([np.zeros((8, 8, 3), np.uint8)], r"photos\[0\]"), (3, "photos")):
        with pytest.raises(InputError, match=match):
            solve_cameras(bad, DEPTH_RANGE)
    for depth_range in ((1.0, 0.1), (0.1,), (np.nan, 1.0), "near"):
        with pytest.raises(InputError, match="depth_range"):
            solve_cameras(good, depth_range)
    with pytest.raises(InputError, match="focal"):
        solve_cameras(good, DEPTH_RANGE, focal=-1.0)


def test_cameras_import_and_run_torch_and_scipy_free():
    code = ("import sys; sys.modules['torch'] = None; sys.modules['scipy'] = None\n"
            "import numpy as np\n"
            "from iris_runtime.cameras import solve_cameras\n"
            "rng = np.random.default_rng(0)\n"
            "im = list(rng.integers(0, 256, (3, 48, 48, 3), dtype=np.uint8))\n"
            "s = solve_cameras(im, (0.1, 1.0))\n"
            "assert s.world_from_cam.shape == (3, 4, 4) and len(s.status) == 3\n"
            "print('ok')\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr

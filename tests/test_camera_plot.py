"""iris_runtime.camera_plot: Umeyama alignment against an independent float64 reference (scipy's
Kabsch rotation + closed-form scale), its degenerate cases, and the frustum picture."""
from __future__ import annotations

import numpy as np
import pytest

from iris_runtime.camera_plot import align_poses, align_similarity, apply_similarity, draw_cameras

Rotation = pytest.importorskip("scipy.spatial.transform").Rotation


def random_rotation(rng):
    return Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()


def reference_similarity(P, Q):
    """Independent least-squares similarity: Kabsch rotation from scipy's ``align_vectors`` on the
    centred points, then the optimal scale and translation in closed form."""
    mp, mq = P.mean(0), Q.mean(0)
    rot, _ = Rotation.align_vectors(Q - mq, P - mp)      # argmin sum |q - R p|^2
    R = rot.as_matrix()
    Pc, Qc = P - mp, Q - mq
    s = float(np.sum(Qc * (Pc @ R.T)) / np.sum(Pc * Pc))
    return s, R, mq - s * R @ mp


def poses(rng, n, spread=1.0):
    T = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        T[k, :3, :3] = random_rotation(rng)
        T[k, :3, 3] = spread * rng.standard_normal(3)
    return T


@pytest.mark.parametrize("scale", [1e-6, 0.37, 1.0, 250.0])
def test_umeyama_recovers_a_known_similarity(scale):
    rng = np.random.default_rng(int(scale * 1000) % 97)
    P = rng.standard_normal((8, 3))
    R = random_rotation(rng)
    t = rng.standard_normal(3) * 5
    Q = scale * P @ R.T + t
    s_hat, R_hat, t_hat = align_similarity(P, Q)
    assert s_hat == pytest.approx(scale, rel=1e-9)
    np.testing.assert_allclose(R_hat, R, atol=1e-9)
    np.testing.assert_allclose(t_hat, t, atol=1e-9 * max(1.0, np.abs(t).max()))
    assert np.linalg.det(R_hat) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_umeyama_matches_an_independent_reference_with_noise(seed):
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(3, 12))
    P = rng.standard_normal((n, 3)) * rng.uniform(0.1, 10)
    Q = 2.3 * P @ random_rotation(rng).T + rng.standard_normal(3) + 0.3 * rng.standard_normal((n, 3))
    s, R, t = align_similarity(P, Q)
    s_ref, R_ref, t_ref = reference_similarity(P, Q)
    assert s == pytest.approx(s_ref, rel=1e-9)
    np.testing.assert_allclose(R, R_ref, atol=1e-9)
    np.testing.assert_allclose(t, t_ref, atol=1e-9)


def test_reflection_is_not_returned():
    rng = np.random.default_rng(3)
    P = rng.standard_normal((6, 3))
    Q = P * np.array([1.0, 1.0, -1.0])                    # a mirror image: best proper rotation
    s, R, t = align_similarity(P, Q)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    s_ref, R_ref, _ = reference_similarity(P, Q)
    np.testing.assert_allclose(R, R_ref, atol=1e-9)
    assert s == pytest.approx(s_ref, rel=1e-9)


def test_collapsed_prediction_falls_back_to_the_first_cameras_rotation():
    rng = np.random.default_rng(4)
    true = poses(rng, 8)
    R_pred0 = random_rotation(rng)
    for centre in ((0.0, 0.0, 0.0), (3e8, -1e8, 2e8)):     # exactly equal, and equal up to rounding
        P = np.tile(np.asarray(centre), (8, 1)) + np.asarray(centre) * 1e-15 * rng.standard_normal((8, 3))
        s, R, t = align_similarity(P, true[:, :3, 3], pred_rotation=R_pred0,
                                   true_rotation=true[0, :3, :3])
        assert s == 0.0
        np.testing.assert_allclose(R, true[0, :3, :3] @ R_pred0.T, atol=1e-12)
        np.testing.assert_allclose(t, true[:, :3, 3].mean(0), atol=1e-12)
    # Without rotations: the identity. One camera is a collapsed set too.
    s, R, t = align_similarity(np.zeros((8, 3)), true[:, :3, 3])
    assert s == 0.0 and np.array_equal(R, np.eye(3))
    s, R, t = align_similarity(np.ones((1, 3)), np.full((1, 3), 2.0))
    assert s == 0.0 and np.allclose(t, 2.0)
    # Collapsed truth: scale 0 as well (every predicted centre goes to the one true centre).
    s, R, t = align_similarity(true[:, :3, 3], np.full((8, 3), 5.0))
    assert s == 0.0 and np.allclose(t, 5.0)


def test_collinear_centres_use_the_first_rotation_for_the_free_twist():
    rng = np.random.default_rng(5)
    for n in (2, 5):
        pred = poses(rng, n)
        d = rng.standard_normal(3)
        pred[:, :3, 3] = np.linspace(-1, 2, n)[:, None] * d + rng.standard_normal(3)
        s0, R0, t0 = 1.7, random_rotation(rng), rng.standard_normal(3)
        true = apply_similarity(pred, s0, R0, t0)
        aligned, (s, R, t) = align_poses(pred, true)
        assert s == pytest.approx(s0, rel=1e-9)
        np.testing.assert_allclose(R, R0, atol=1e-9)
        np.testing.assert_allclose(aligned, true, atol=1e-9)


def test_align_poses_puts_predictions_in_the_true_frame():
    rng = np.random.default_rng(6)
    pred = poses(rng, 8)
    true = apply_similarity(pred, 0.2, random_rotation(rng), rng.standard_normal(3))
    aligned, (s, R, t) = align_poses(pred, true)
    np.testing.assert_allclose(aligned, true, atol=1e-9)
    np.testing.assert_allclose(aligned[:, :3, :3] @ aligned[:, :3, :3].transpose(0, 2, 1),
                               np.broadcast_to(np.eye(3), (8, 3, 3)), atol=1e-12)


def test_bad_input_is_a_typed_error():
    from iris_runtime.errors import InputError
    with pytest.raises(InputError):
        align_similarity(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(InputError):
        align_similarity(np.full((3, 3), np.nan), np.zeros((3, 3)))
    with pytest.raises(InputError):
        draw_cameras(np.zeros((3, 3)))
    with pytest.raises(InputError):
        draw_cameras(np.eye(4), size=(8, 8))


# ----------------------------------------------------------------------------------------------
# Pictures
# ----------------------------------------------------------------------------------------------

def check_image(img, size):
    assert isinstance(img, np.ndarray) and img.dtype == np.uint8 and img.shape == (*size, 3)
    assert img.flags.c_contiguous
    background = (img == 255).all(-1)
    # Not blank: some pixels are drawn, in colour (the frustums), not only black text.
    assert (~background).mean() > 0.005
    coloured = (img.max(-1).astype(int) - img.min(-1)) > 60
    assert coloured.sum() > 50


def arc(n=8, radius=0.6, arc_deg=60.0):
    T = np.tile(np.eye(4), (n, 1, 1))
    for k, a in enumerate(np.radians(np.linspace(0, arc_deg, n))):
        c, s = np.cos(a), np.sin(a)
        R = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])          # looking at the origin
        T[k, :3, :3] = R
        T[k, :3, 3] = -radius * R[:, 2]
    return T


K = np.array([[70.0, 0, 32], [0, 70.0, 32], [0, 0, 1]])


@pytest.mark.parametrize("size", [(360, 480), (64, 96), (720, 960)])
def test_picture_of_predicted_and_true_cameras(size):
    true = arc()
    pred = true.copy()
    pred[:, :3, 3] = pred[:, :3, 3] * 3.0 + 0.01 * np.random.default_rng(0).standard_normal((8, 3))
    aligned, _ = align_poses(pred, true)
    img = draw_cameras(aligned, [1.1, 1.1], reference=true, reference_focal=K, size=size,
                       title="scene")
    check_image(img, size)
    blue = (img[..., 2].astype(int) - img[..., 0] > 80).sum()
    red = (img[..., 0].astype(int) - img[..., 2] > 80).sum()
    assert blue > 20 and red > 20                     # both sets visible


@pytest.mark.parametrize("size", [(450, 700), (64, 96)])
def test_a_further_set_of_cameras_is_drawn_in_its_colour(size):
    """Three sets (true, predicted, and a further one holding some of the frames, e.g. the camera
    head's references beside a solve): the further set's frustums appear in its colour (and
    nowhere without it), also in a small picture whose legend takes a second line."""
    from iris_runtime.camera_plot import OTHER_COLOUR, CameraSet
    from iris_runtime.errors import InputError
    true = arc()
    frames = [0, 2, 3, 5, 7]
    head = true[frames].copy()
    head[:, :3, 3] += np.array([0.0, -0.15, 0.0])          # beside the true ones, not on them
    other = CameraSet(head, [1.1, 1.1], "camera head (references)", labels=frames)
    two = draw_cameras(true, K, reference=true, size=size, names=("rendered (epipolar)", "true"))
    three = draw_cameras(true, K, reference=true, size=size, others=[other],
                         names=("rendered (epipolar)", "true"))
    check_image(three, size)
    green = (np.abs(three.astype(int) - OTHER_COLOUR).sum(-1) < 30).sum()
    assert green > 20 and (np.abs(two.astype(int) - OTHER_COLOUR).sum(-1) < 30).sum() == 0
    with pytest.raises(InputError, match=r"others\[0\].labels"):
        draw_cameras(true, K, others=[CameraSet(head, labels=[0, 1])])
    with pytest.raises(InputError, match=r"others\[0\].world_from_cam"):
        draw_cameras(true, K, others=[CameraSet(np.zeros((2, 3)))])
    with pytest.raises(InputError, match="CameraSet"):
        draw_cameras(true, K, others=[head])


@pytest.mark.parametrize("case", ["one-camera", "all-at-one-point", "collapsed-vs-true", "huge",
                                  "tiny", "non-rigid", "non-finite", "per-view-K", "no-focal"])
def test_degenerate_cameras_still_give_a_picture(case):
    true = arc()
    ref, focal = None, K
    if case == "one-camera":
        cams = true[:1]
    elif case == "all-at-one-point":
        cams = np.tile(np.eye(4), (8, 1, 1))
    elif case == "collapsed-vs-true":
        cams, _ = align_poses(np.tile(np.eye(4), (8, 1, 1)), true)
        ref = true
    elif case == "huge":
        cams = true.copy()
        cams[:, :3, 3] = cams[:, :3, 3] * 1e9 + 1e12
    elif case == "tiny":
        cams = true.copy()
        cams[:, :3, 3] *= 1e-12
    elif case == "non-rigid":
        cams = true.copy()
        cams[:, :3, :3] *= np.array([2.0, 0.0, 1.0])    # a singular "rotation"
    elif case == "non-finite":
        cams = true.copy()
        cams[2, 0, 3] = np.nan
        cams[3, 1, 1] = np.inf
    elif case == "per-view-K":
        cams, focal = true, np.stack([K * [[1 + 0.1 * k], [1], [1]] for k in range(8)])
    else:
        cams, focal = true, None
    img = draw_cameras(cams, focal, reference=ref, size=(240, 320))
    check_image(img, (240, 320))


@pytest.mark.parametrize("magnitude", [1e-200, 1e200])
def test_extreme_coordinates_neither_warn_nor_lose_the_alignment(magnitude):
    import warnings
    rng = np.random.default_rng(8)
    true = arc()
    true[:, :3, 3] *= magnitude
    pred = apply_similarity(true, 0.5, random_rotation(rng), magnitude * rng.standard_normal(3))
    pred[:, :3, :3] *= magnitude                          # a badly scaled "rotation" too
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        aligned, (s, R, t) = align_poses(pred, true)
        check_image(draw_cameras(aligned, K, reference=true, size=(120, 160)), (120, 160))
        check_image(draw_cameras(pred, K, size=(120, 160)), (120, 160))
    assert s == pytest.approx(2.0, rel=1e-9)
    np.testing.assert_allclose(aligned[:, :3, 3] / magnitude, true[:, :3, 3] / magnitude, atol=1e-9)


@pytest.mark.parametrize("focal", [0.0, 1e-320, [1e-310, 1e300], np.nan,
                                   np.array([[1e-310, 0, 1e300], [0, 1e-310, 1e300], [0, 0, 1]])],
                         ids=["zero", "subnormal", "subnormal-pair", "nan", "subnormal-K"])
def test_a_degenerate_focal_draws_the_default_frustums_without_warning(focal):
    """0.5 / f or cx / fx of such a focal is inf or NaN (a subnormal one overflowed with a
    RuntimeWarning): the frustums fall back to the default extents, silently."""
    import warnings
    true = arc()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        img = draw_cameras(true, focal, size=(120, 160))
    np.testing.assert_array_equal(img, draw_cameras(true, None, size=(120, 160)))


def test_picture_is_deterministic_and_scale_free():
    true = arc()
    a = draw_cameras(true, K)
    b = draw_cameras(true, K)
    assert np.array_equal(a, b)
    big = true.copy()
    big[:, :3, 3] *= 1000.0
    c = draw_cameras(big, K)
    # The same drawing up to the scale bar's label: the frustum area is the same.
    body = slice(30, 300)
    assert np.array_equal(a[body] == 255, c[body] == 255)


def test_iris_render_writes_a_picture_of_the_predicted_cameras(model_dir, tmp_path, capsys):
    from PIL import Image

    from iris_runtime.cli import main as render_main
    rng = np.random.default_rng(3)
    paths = []
    for k in range(3):
        paths.append(tmp_path / f"{k}.png")
        Image.fromarray(rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)).save(paths[-1])
    out = tmp_path / "out"
    code = render_main([str(model_dir), *map(str, paths), "-o", str(out), "--view", "1",
                        "--size", "8x8", "--no-depth", "--threads", "1"])
    assert code == 0, capsys.readouterr().err
    assert "cameras.png" in capsys.readouterr().out
    img = np.asarray(Image.open(out / "cameras.png"))
    check_image(img, (480, 640))

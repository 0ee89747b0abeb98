"""Step 5 of the camera solve, and the refinement's adjustment: bundle adjustment, the poses,
the points and the one shared focal refined together on the reprojection error of every
observation (``bundle_adjust``).

Levenberg-Marquardt on the normal equations with the points eliminated (Schur complement: one
3x3 block per point, a dense system the size of the cameras), Cauchy-reweighted so that a wrong
match does not drag the cameras, with Nielsen's damping. Written here in numpy because the
runtime has no SciPy, and because ``scipy.optimize.least_squares`` (trust region, sparse
Jacobian, LSMR) left the focal where it started on the same problems (docs/record/cameras.md,
"Bundle adjustment in numpy"); tests/test_cameras.py checks that it reaches the minimum that
SciPy's dense trust-region solver reaches from the same start.

Parametrisation: ``cam_from_world`` rotations ``R [V, 3, 3]`` updated on the left (R <- exp(w) R)
and translations ``t [V, 3]``; one focal in pixels with the principal point at the image centre
(square pixels, no distortion). One view is held fixed (the gauge) and one coordinate of another
view's translation (the scale, which the images cannot fix).

The camera solve (``mapper``) and the refinement of a model's cameras (``refine.rounds``, the
witness's mapping) both run it. Until SOLVE_VERSION 12 of ``iris_train.pseudo_poses`` the solve
ran an adjuster of its own on the same cost (damping divided and multiplied by 10), kept so that
the teacher store stayed as solved (docs/record/cameras-refactor.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BundleResult", "bundle_adjust", "reprojection_errors", "project"]

#: A step that lowers the cost by less than this fraction of it ends the adjustment.
RELATIVE_TOLERANCE = 1e-6
#: An accepted step divides the damping by at most this much (Nielsen's rule).
MAX_DAMPING_FALL = 3.0


@dataclass(frozen=True)
class BundleResult:
    """R [V, 3, 3], t [V, 3] (cam_from_world), focal (pixels), points [P, 3], the robust cost
    at the end and the iterations run."""
    R: np.ndarray
    t: np.ndarray
    focal: float
    points: np.ndarray
    cost: float
    iterations: int


def project(R, t, focal, centre, points):
    """Camera coordinates ``Y [P, V, 3]`` and pixels ``[P, V, 2]`` of every point in every view."""
    Y = np.matmul(points[None], R.transpose(0, 2, 1)).transpose(1, 0, 2) + t[None]
    z = np.where(np.abs(Y[..., 2]) > 1e-12, Y[..., 2], 1e-12)
    return Y, focal * Y[..., :2] / z[..., None] + centre


def reprojection_errors(R, t, focal, centre, points, uv) -> tuple[np.ndarray, np.ndarray]:
    """Pixel distance [P, V] between each observation ``uv [P, V, 2]`` and its point's projection,
    and the point's depth z [P, V] in each camera."""
    Y, proj = project(R, t, focal, centre, points)
    return np.linalg.norm(proj - uv, axis=-1), Y[..., 2]


def _write_inverse_factor(Q, A):
    """``Q [3, 3, ...]`` lower triangular (zero above the diagonal, written in place) with
    ``A^-1 = Q^T Q`` for the symmetric positive definite 3x3 matrices ``A [3, 3, ...]`` (the 3x3
    axes first): the inverse of their Cholesky factor (A = L L^T, Q = L^-1), written out, one
    vectorised pass over all of them. Cholesky is backward stable, so a far point's block,
    whose depth is barely observed, is inverted as accurately as LAPACK does it (cofactors are
    not: they lose the square of the condition)."""
    a, b, c = A[0, 0], A[0, 1], A[0, 2]
    d, e, g = A[1, 1], A[1, 2], A[2, 2]
    l00 = np.sqrt(a)
    l10, l20 = b / l00, c / l00
    l11 = np.sqrt(d - l10 * l10)
    l21 = (e - l20 * l10) / l11
    l22 = np.sqrt(g - l20 * l20 - l21 * l21)
    Q[0, 0], Q[1, 1], Q[2, 2] = 1.0 / l00, 1.0 / l11, 1.0 / l22
    Q[1, 0] = -l10 * Q[0, 0] * Q[1, 1]
    Q[2, 1] = -l21 * Q[1, 1] * Q[2, 2]
    Q[2, 0] = -(l20 * Q[0, 0] + l21 * Q[1, 0]) * Q[2, 2]


def _free_entries(v: np.ndarray, t: np.ndarray, fixed_view: int, scale_view: int) -> np.ndarray:
    """bool [V, 7]: the free entries of each view's (rotation, translation, focal) in an
    adjustment whose observations are in views ``v [n]``: the pose of every observed view but
    the fixed one, less the scale view's largest translation coordinate (``t [V, 3]``). The
    focal column is False; the caller adds it as one shared parameter."""
    free = np.zeros((len(t), 7), bool)
    free[np.unique(v), :6] = True
    free[fixed_view] = False
    free[scale_view, 3 + int(np.argmax(np.abs(t[scale_view])))] = False
    return free


def _exp_so3(w: np.ndarray) -> np.ndarray:
    """exp([w]_x) [V, 3, 3] of rotation vectors w [V, 3] (Rodrigues' formula)."""
    theta = np.linalg.norm(w, axis=1)
    k = w / np.where(theta > 0, theta, 1.0)[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    return (np.eye(3) + np.sin(theta)[:, None, None] * K
            + (1.0 - np.cos(theta))[:, None, None] * (K @ K))


def bundle_adjust(R, t, focal, centre, points, uv, active, *, fixed_view: int, scale_view: int,
                  refine_focal: bool = True, loss_scale: float = 1.0,
                  max_iterations: int = 50,
                  tolerance: float = RELATIVE_TOLERANCE) -> BundleResult:
    """Refine ``R [V, 3, 3]``, ``t [V, 3]`` (cam_from_world), ``focal`` (pixels; principal point
    ``centre`` [2]) and ``points [P, 3]`` on the observations ``uv [P, V, 2]`` where ``active
    [P, V]`` is True.

    The cost: ``0.5 s^2 sum log(1 + |r|^2 / s^2)`` over the active observations (Cauchy, scale
    ``s = loss_scale`` pixels), ``r`` the pixel residual ``focal Y_xy / Y_z + centre - uv`` of
    the point in its camera, ``Y = R_v X_p + t_v``; infinite while a point is behind a camera
    or the focal is not positive.

    The parameters: a rotation vector per view applied on the left (``R_v <- exp([w_v]_x) R_v``),
    the translations, the points and, with ``refine_focal``, the one focal. View ``fixed_view``
    does not move (the gauge), nor the largest coordinate of view ``scale_view``'s translation
    (the scale); a view no active observation sees and a point none sees stay as given.

    Each step solves the Gauss-Newton normal equations of the Cauchy-reweighted residuals
    (weights ``1 / (1 + |r|^2 / s^2)``), damped by ``lam`` times their diagonal (Marquardt),
    with the points eliminated (Schur complement). The damping, 1e-3 at the start, moves by
    Nielsen's rule (Madsen, Nielsen & Tingleff, "Methods for non-linear least squares problems",
    2004): a step that lowers the cost is taken, and ``lam`` is multiplied by
    ``max(1 / MAX_DAMPING_FALL, 1 - (2 rho - 1)^3)``, ``rho`` the cost's fall over the fall the
    damped linear model predicted (``lam`` no lower than 1e-10); a step that does not is
    rejected and ``lam`` multiplied by 2, then 4, 8... (the factor doubling with each rejection
    in a row) until one is taken. (The point blocks also get 1e-9 on their diagonal, the
    reduced camera system 1e-12, so that a point or a view the observations barely fix does
    not make them singular.)

    Stops after ``max_iterations`` accepted steps, at the first accepted step that lowers the
    cost by less than ``tolerance`` of it, or when the damping passes 1e10 (no step lowers the
    cost). Returns the cost at the end and the iterations run (0 when nothing is observed: the
    start back unchanged)."""
    # Layout: per-observation arrays have the observations last (``J [2, 11, n]``: each entry
    # of the Jacobian, and the residual as its 11th column, one row each), written into buffers
    # allocated once. The per-view sums are matrix products per view, the per-point sums one
    # ``reduceat``. The Schur complement's sum over points is ``M^T M`` of ``M [3P, n_free]``
    # (``Q_p W_p^T`` per point, ``V_p^-1 = Q_p^T Q_p``), written into the free parameters'
    # columns; both solves against the point blocks go through ``M`` and ``Q``. The residuals
    # of an accepted step are the next step's.
    R, t, X = np.array(R, np.float64), np.array(t, np.float64), np.array(points, np.float64)
    f = float(focal)
    uv, active = np.asarray(uv, np.float64), np.asarray(active, bool)
    centre, s2 = np.asarray(centre, np.float64)[:, None], float(loss_scale) ** 2
    V, P = R.shape[0], X.shape[0]
    p, v = np.nonzero(active)                          # the observations, sorted by point
    n = len(p)
    if n == 0:
        return BundleResult(R, t, f, X, 0.0, 0)
    uv = uv[p, v].T                                                    # [2, n]
    starts = np.flatnonzero(np.r_[True, p[1:] != p[:-1]])
    seen = p[starts]                                                   # the observed points
    by_view = np.argsort(v, kind="stable")
    view_ends = np.searchsorted(v[by_view], np.arange(V + 1))
    # Where each observation's R_v X_p lies in (R.reshape(3V, 3) @ X.T).ravel(): [3, n].
    coords = (3 * v + np.arange(3)[:, None]) * P + p

    # T [7V, n_free]: per-view entries from the parameters (the focal shared by every view).
    free = _free_entries(v, t, fixed_view, scale_view)
    n_pose = int(free.sum())
    n_free = n_pose + int(refine_focal)
    T = np.zeros((7 * V, n_free))
    T[np.flatnonzero(free.ravel()), np.arange(n_pose)] = 1.0
    if refine_focal:
        T[6::7, n_pose] = 1.0
    # M's entries: G [3, 7, n] (Q_p W_o^T of each observation o of point p) at row 3 p + i and
    # the column of its view's free pose entry j (fixed entries dropped); the focal's column
    # sums the point's observations.
    column = -np.ones((V, 7), np.int64)
    column[free] = np.arange(n_pose)
    column = np.broadcast_to(column[v, :6].T, (3, 6, n))
    kept = column >= 0
    into_M = ((3 * p + np.arange(3)[:, None, None]) * n_free + column)[kept]
    from_G = np.arange(3 * 7 * n).reshape(3, 7, n)[:, :6][kept]
    focal_rows = 3 * seen + np.arange(3)[:, None]                      # [3, P_seen]
    M = np.zeros((3 * P, n_free))
    J, J_by_view = np.empty((2, 11, n)), np.empty((2, 11, n))
    Wo, Pw, G = np.empty((7, 3, n)), np.empty((3, 4, n)), np.empty((3, 7, n))
    Wo_k, Pw_k, R_v = np.empty((7, 3, n)), np.empty((3, 4, n)), np.empty((3, 3, n))
    H, U = np.empty((V, 11, 11)), np.zeros((V, 7, V, 7))
    Vp, gp, Q = np.zeros((3, 3, P)), np.zeros((3, P)), np.zeros((3, 3, P))

    def residuals(R, t, f, X):
        """The cost and (camera coordinates Y [3, n] = a + t_v with a = R_v X_p, 1 / depth
        [n], residuals [2, n]): the cost infinite with a point behind its camera."""
        a = (R.reshape(3 * V, 3) @ X.T).ravel()[coords]
        Y = a + t[v].T
        ahead = Y[2] > 1e-12
        iz = 1.0 / np.where(ahead, Y[2], 1e-12)
        r = f * Y[:2] * iz + centre - uv
        cost = float(0.5 * s2 * np.log1p((r * r).sum(0) / s2).sum()) \
            if ahead.all() and f > 0 else np.inf                                  # Cauchy
        return cost, (Y, a, iz, r)

    cost, state = residuals(R, t, f, X)
    lam, nu, it = 1e-3, 2.0, 0
    for it in range(1, max_iterations + 1):
        Y, a, iz, r = state
        # d(pixel)/dY = [[fz, 0, gx], [0, fz, gy]]; the rotation's columns are its product with
        # d(exp(w) a)/dw = -[a]_x, the point's with R_v. Rows scaled by the square roots of
        # the Cauchy IRLS weights.
        fz = f * iz
        gx, gy = -Y[0] * fz * iz, -Y[1] * fz * iz
        np.take(R.transpose(1, 2, 0), v, axis=2, out=R_v)
        J[0, 0], J[0, 1], J[0, 2] = gx * a[1], fz * a[2] - gx * a[0], -fz * a[1]
        J[1, 0], J[1, 1], J[1, 2] = gy * a[1] - fz * a[2], -gy * a[0], fz * a[0]
        J[0, 3], J[0, 4], J[0, 5] = fz, 0.0, gx
        J[1, 3], J[1, 4], J[1, 5] = 0.0, fz, gy
        J[:, 6] = Y[:2] * iz
        J[0, 7:10] = fz * R_v[0] + gx * R_v[2]
        J[1, 7:10] = fz * R_v[1] + gy * R_v[2]
        J[:, 10] = r
        J *= 1.0 / np.sqrt(1.0 + (r * r).sum(0) / s2)
        # Per view: [J r]^T [J r] over its observations holds U_v [7, 7] and g_v [7].
        np.take(J, by_view, axis=2, out=J_by_view)
        for k in range(V):
            B = J_by_view[:, :, view_ends[k]:view_ends[k + 1]]
            np.matmul(B[0], B[0].T, out=H[k])
            H[k] += B[1] @ B[1].T
        U[np.arange(V), :, np.arange(V)] = H[:, :7, :7]
        Ur = T.T @ U.reshape(7 * V, 7 * V) @ T
        gr = T.T @ H[:, :7, 10].ravel()
        # Per observation W_o [7, 3]; per point V_p [3, 3] and g_p [3].
        np.multiply(J[0, :7, None], J[0, None, 7:10], out=Wo)
        Wo += np.multiply(J[1, :7, None], J[1, None, 7:10], out=Wo_k)
        np.multiply(J[0, 7:10, None], J[0, None, 7:11], out=Pw)
        Pw += np.multiply(J[1, 7:10, None], J[1, None, 7:11], out=Pw_k)
        per_point = np.add.reduceat(Pw, starts, axis=2)                # [3, 4, P_seen]
        Vp[:, :, seen], gp[:, seen] = per_point[:, :3], per_point[:, 3]
        diag_U = np.diag(Ur)
        diag_V = np.stack([Vp[0, 0], Vp[1, 1], Vp[2, 2]])              # [3, P]
        damped = Vp.copy()
        done = False
        while True:
            for i in range(3):
                damped[i, i] = Vp[i, i] + (lam * diag_V[i] + 1e-9)
            _write_inverse_factor(Q, damped)
            Q_p = Q[:, :, p]                                            # [3, 3, n]
            np.multiply(Q_p[:, 0, None], Wo[None, :, 0], out=G)         # G = Q_p W_o^T
            G[1:] += Q_p[1:, 1, None] * Wo[None, :, 1]
            G[2] += Q_p[2, 2] * Wo[:, 2]
            M.reshape(-1)[into_M] = G.reshape(-1)[from_G]
            if refine_focal:
                M[focal_rows, n_pose] = np.add.reduceat(G[:, 6], starts, axis=1)
            S = Ur + lam * np.diag(diag_U) - M.T @ M
            Qg = np.stack([Q[0, 0] * gp[0], Q[1, 0] * gp[0] + Q[1, 1] * gp[1],
                           Q[2, 0] * gp[0] + Q[2, 1] * gp[1] + Q[2, 2] * gp[2]])  # [3, P]
            rhs = gr - Qg.T.ravel() @ M                                 # g - W V^-1 g_p
            try:
                dc = -np.linalg.solve(S + 1e-12 * np.eye(n_free), rhs)
            except np.linalg.LinAlgError:
                dc = np.full(n_free, np.nan)
            new = np.inf
            if np.all(np.isfinite(dc)):
                d7 = (T @ dc).reshape(V, 7)                             # 0 where fixed
                q = Qg + (M @ dc).reshape(P, 3).T                       # Q (g_p + W^T dc)
                dp = -np.stack([Q[0, 0] * q[0] + Q[1, 0] * q[1] + Q[2, 0] * q[2],
                                Q[1, 1] * q[1] + Q[2, 1] * q[2], Q[2, 2] * q[2]])
                R2, t2, f2 = _exp_so3(d7[:, :3]) @ R, t + d7[:, 3:6], f + d7[0, 6]
                X2 = X + dp.T
                new, state2 = residuals(R2, t2, f2, X2)
            if new < cost:
                # The fall the damped linear model predicts: (dx^T (lam D dx - g)) / 2.
                predicted = 0.5 * (lam * (diag_U @ dc**2 + (diag_V * dp**2).sum())
                                   - gr @ dc - (gp * dp).sum())
                rho = (cost - new) / predicted if predicted > 0 else 1.0
                done = (cost - new) < tolerance * cost
                R, t, f, X, cost, state = R2, t2, f2, X2, new, state2
                fall = max(1.0 / MAX_DAMPING_FALL, 1.0 - (2.0 * rho - 1.0) ** 3)
                lam, nu = max(lam * fall, 1e-10), 2.0
                break
            lam, nu = lam * nu, 2.0 * nu
            if lam > 1e10:
                break
        if lam > 1e10 or done:
            break
    return BundleResult(R, t, f, X, cost, it)

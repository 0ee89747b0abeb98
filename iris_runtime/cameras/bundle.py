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
from typing import NamedTuple

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


class _NormalEquations(NamedTuple):
    """The Gauss-Newton normal equations of one step, before damping: the cameras' block
    ``Ur [n_free, n_free]`` and gradient ``gr [n_free]`` in the free parameters, the camera-point
    blocks ``Wo [7, 3, n]`` per observation, the point blocks ``Vp [3, 3, P]`` and gradients
    ``gp [3, P]``, and the diagonals the damping scales (``diag_U [n_free]``, ``diag_V [3, P]``).
    Wo, Vp and gp are the adjustment's buffers: valid until its next ``normal_equations``."""
    Ur: np.ndarray
    gr: np.ndarray
    diag_U: np.ndarray
    Wo: np.ndarray
    Vp: np.ndarray
    gp: np.ndarray
    diag_V: np.ndarray


class _Adjustment:
    """What stays fixed while ``bundle_adjust`` iterates: the observations (sorted by point,
    indexed by view), the map from the free parameters to the views' entries, where the
    reduced camera system's entries come from, and the buffers every step writes.

    Layout: per-observation arrays have the observations last (``J [2, 11, n]``: each entry
    of the Jacobian, and the residual as its 11th column, one row each), written into buffers
    allocated once. The per-view sums are matrix products per view, the per-point sums one
    ``reduceat``. The Schur complement's sum over points is ``M^T M`` of ``M [3P, n_free]``
    (``Q_p W_p^T`` per point, ``V_p^-1 = Q_p^T Q_p``), written into the free parameters'
    columns; both solves against the point blocks go through ``M`` and ``Q``."""

    def __init__(self, p, v, uv, centre, s2, V, P, t, *, fixed_view, scale_view, refine_focal):
        """The observations ``(p, v)`` (point, view; sorted by point) of pixels ``uv [P, V, 2]``,
        principal point ``centre [2, 1]``, squared loss scale ``s2``, ``V`` views (translations
        ``t [V, 3]``, for the scale view's held coordinate) and ``P`` points."""
        n = len(p)
        self.p, self.v, self.V, self.P = p, v, V, P
        self.uv, self.centre, self.s2 = uv[p, v].T, centre, s2             # uv [2, n]
        self.starts = np.flatnonzero(np.r_[True, p[1:] != p[:-1]])
        self.seen = p[self.starts]                                     # the observed points
        self.by_view = np.argsort(v, kind="stable")
        self.view_ends = np.searchsorted(v[self.by_view], np.arange(V + 1))
        # Where each observation's R_v X_p lies in (R.reshape(3V, 3) @ X.T).ravel(): [3, n].
        self.coords = (3 * v + np.arange(3)[:, None]) * P + p
        self.refine_focal = refine_focal
        self._map_free_parameters(_free_entries(v, t, fixed_view, scale_view))
        self.J, self.J_by_view = np.empty((2, 11, n)), np.empty((2, 11, n))
        self.Wo, self.Pw, self.G = np.empty((7, 3, n)), np.empty((3, 4, n)), np.empty((3, 7, n))
        self.Wo_k, self.Pw_k = np.empty((7, 3, n)), np.empty((3, 4, n))
        self.R_v = np.empty((3, 3, n))
        self.H, self.U = np.empty((V, 11, 11)), np.zeros((V, 7, V, 7))
        self.Vp, self.gp, self.Q = np.zeros((3, 3, P)), np.zeros((3, P)), np.zeros((3, 3, P))

    def _map_free_parameters(self, free):
        """The free parameters of the views' entries ``free [V, 7]`` (and, with
        ``refine_focal``, the shared focal): their map ``T`` to the views' entries, their count
        ``n_free`` (``n_pose`` of them the poses'), and ``M`` with the indices that fill it."""
        V, P, p, v, n = self.V, self.P, self.p, self.v, len(self.p)
        # T [7V, n_free]: per-view entries from the parameters (the focal shared by every view).
        self.n_pose = n_pose = int(free.sum())
        self.n_free = n_free = n_pose + int(self.refine_focal)
        self.T = np.zeros((7 * V, n_free))
        self.T[np.flatnonzero(free.ravel()), np.arange(n_pose)] = 1.0
        if self.refine_focal:
            self.T[6::7, n_pose] = 1.0
        # M's entries: G [3, 7, n] (Q_p W_o^T of each observation o of point p) at row 3 p + i and
        # the column of its view's free pose entry j (fixed entries dropped); the focal's column
        # sums the point's observations.
        column = -np.ones((V, 7), np.int64)
        column[free] = np.arange(n_pose)
        column = np.broadcast_to(column[v, :6].T, (3, 6, n))
        kept = column >= 0
        self.into_M = ((3 * p + np.arange(3)[:, None, None]) * n_free + column)[kept]
        self.from_G = np.arange(3 * 7 * n).reshape(3, 7, n)[:, :6][kept]
        self.focal_rows = 3 * self.seen + np.arange(3)[:, None]          # [3, P_seen]
        self.M = np.zeros((3 * P, n_free))

    def residuals(self, R, t, f, X):
        """The cost and (camera coordinates Y [3, n] = a + t_v with a = R_v X_p, 1 / depth
        [n], residuals [2, n]): the cost infinite with a point behind its camera."""
        a = (R.reshape(3 * self.V, 3) @ X.T).ravel()[self.coords]
        Y = a + t[self.v].T
        ahead = Y[2] > 1e-12
        iz = 1.0 / np.where(ahead, Y[2], 1e-12)
        r = f * Y[:2] * iz + self.centre - self.uv
        s2 = self.s2
        cost = float(0.5 * s2 * np.log1p((r * r).sum(0) / s2).sum()) \
            if ahead.all() and f > 0 else np.inf                                  # Cauchy
        return cost, (Y, a, iz, r)

    def _weighted_jacobian(self, R, f, state):
        """``J [2, 11, n]``: each observation's Jacobian row by row (rotation, translation,
        focal, point) and its residual as the 11th column, weighted, at ``state``."""
        Y, a, iz, r = state
        J, R_v = self.J, self.R_v
        # d(pixel)/dY = [[fz, 0, gx], [0, fz, gy]]; the rotation's columns are its product with
        # d(exp(w) a)/dw = -[a]_x, the point's with R_v. Rows scaled by the square roots of
        # the Cauchy IRLS weights.
        fz = f * iz
        gx, gy = -Y[0] * fz * iz, -Y[1] * fz * iz
        np.take(R.transpose(1, 2, 0), self.v, axis=2, out=R_v)
        J[0, 0], J[0, 1], J[0, 2] = gx * a[1], fz * a[2] - gx * a[0], -fz * a[1]
        J[1, 0], J[1, 1], J[1, 2] = gy * a[1] - fz * a[2], -gy * a[0], fz * a[0]
        J[0, 3], J[0, 4], J[0, 5] = fz, 0.0, gx
        J[1, 3], J[1, 4], J[1, 5] = 0.0, fz, gy
        J[:, 6] = Y[:2] * iz
        J[0, 7:10] = fz * R_v[0] + gx * R_v[2]
        J[1, 7:10] = fz * R_v[1] + gy * R_v[2]
        J[:, 10] = r
        J *= 1.0 / np.sqrt(1.0 + (r * r).sum(0) / self.s2)
        return J

    def normal_equations(self, R, f, state) -> _NormalEquations:
        """The normal equations at ``state`` (what ``residuals`` returned for ``R``, ``f`` and
        the points)."""
        J = self._weighted_jacobian(R, f, state)
        J_by_view, H, U, T, V = self.J_by_view, self.H, self.U, self.T, self.V
        Wo, Pw, Vp, gp = self.Wo, self.Pw, self.Vp, self.gp
        # Per view: [J r]^T [J r] over its observations holds U_v [7, 7] and g_v [7].
        np.take(J, self.by_view, axis=2, out=J_by_view)
        for k in range(V):
            B = J_by_view[:, :, self.view_ends[k]:self.view_ends[k + 1]]
            np.matmul(B[0], B[0].T, out=H[k])
            H[k] += B[1] @ B[1].T
        U[np.arange(V), :, np.arange(V)] = H[:, :7, :7]
        Ur = T.T @ U.reshape(7 * V, 7 * V) @ T
        gr = T.T @ H[:, :7, 10].ravel()
        # Per observation W_o [7, 3]; per point V_p [3, 3] and g_p [3].
        np.multiply(J[0, :7, None], J[0, None, 7:10], out=Wo)
        Wo += np.multiply(J[1, :7, None], J[1, None, 7:10], out=self.Wo_k)
        np.multiply(J[0, 7:10, None], J[0, None, 7:11], out=Pw)
        Pw += np.multiply(J[1, 7:10, None], J[1, None, 7:11], out=self.Pw_k)
        per_point = np.add.reduceat(Pw, self.starts, axis=2)           # [3, 4, P_seen]
        Vp[:, :, self.seen], gp[:, self.seen] = per_point[:, :3], per_point[:, 3]
        diag_V = np.stack([Vp[0, 0], Vp[1, 1], Vp[2, 2]])              # [3, P]
        return _NormalEquations(Ur, gr, np.diag(Ur), Wo, Vp, gp, diag_V)

    def _reduced_camera_system(self, eq: _NormalEquations, lam: float):
        """The damped system in the cameras with the points eliminated (``S dc = -rhs``) and
        ``Qg [3, P]`` (``Q_p g_p``), leaving ``Q`` (``V_p^-1 = Q_p^T Q_p`` of the damped point
        blocks) and ``M`` written."""
        Q, M, G, Wo, Vp, gp = self.Q, self.M, self.G, eq.Wo, eq.Vp, eq.gp
        damped = Vp.copy()
        for i in range(3):
            damped[i, i] = Vp[i, i] + (lam * eq.diag_V[i] + 1e-9)
        _write_inverse_factor(Q, damped)
        Q_p = Q[:, :, self.p]                                          # [3, 3, n]
        np.multiply(Q_p[:, 0, None], Wo[None, :, 0], out=G)            # G = Q_p W_o^T
        G[1:] += Q_p[1:, 1, None] * Wo[None, :, 1]
        G[2] += Q_p[2, 2] * Wo[:, 2]
        M.reshape(-1)[self.into_M] = G.reshape(-1)[self.from_G]
        if self.refine_focal:
            M[self.focal_rows, self.n_pose] = np.add.reduceat(G[:, 6], self.starts, axis=1)
        S = eq.Ur + lam * np.diag(eq.diag_U) - M.T @ M
        Qg = np.stack([Q[0, 0] * gp[0], Q[1, 0] * gp[0] + Q[1, 1] * gp[1],
                       Q[2, 0] * gp[0] + Q[2, 1] * gp[1] + Q[2, 2] * gp[2]])  # [3, P]
        rhs = eq.gr - Qg.T.ravel() @ M                                 # g - W V^-1 g_p
        return S, rhs, Qg

    def damped_step(self, eq: _NormalEquations, lam: float):
        """The step ``(dc [n_free], dp [3, P])`` of the free parameters and the points damped
        by ``lam``: the reduced camera system solved, the points back-substituted; None when
        the system has no finite solution."""
        S, rhs, Qg = self._reduced_camera_system(eq, lam)
        try:
            dc = -np.linalg.solve(S + 1e-12 * np.eye(self.n_free), rhs)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(dc)):
            return None
        Q = self.Q
        q = Qg + (self.M @ dc).reshape(self.P, 3).T                    # Q (g_p + W^T dc)
        dp = -np.stack([Q[0, 0] * q[0] + Q[1, 0] * q[1] + Q[2, 0] * q[2],
                        Q[1, 1] * q[1] + Q[2, 1] * q[2], Q[2, 2] * q[2]])
        return dc, dp

    def moved(self, R, t, f, X, dc, dp):
        """``R``, ``t``, ``f``, ``X`` moved by the step ``(dc, dp)`` (rotations on the left)."""
        d7 = (self.T @ dc).reshape(self.V, 7)                          # 0 where fixed
        return _exp_so3(d7[:, :3]) @ R, t + d7[:, 3:6], f + d7[0, 6], X + dp.T


def _predicted_fall(eq: _NormalEquations, lam: float, dc, dp) -> float:
    """The fall the damped linear model predicts: (dx^T (lam D dx - g)) / 2."""
    return 0.5 * (lam * (eq.diag_U @ dc**2 + (eq.diag_V * dp**2).sum())
                  - eq.gr @ dc - (eq.gp * dp).sum())


def _nielsen_damping(lam: float, rho: float) -> float:
    """The damping after an accepted step whose cost fell ``rho`` times the predicted fall."""
    fall = max(1.0 / MAX_DAMPING_FALL, 1.0 - (2.0 * rho - 1.0) ** 3)
    return max(lam * fall, 1e-10)


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
    R, t, X = np.array(R, np.float64), np.array(t, np.float64), np.array(points, np.float64)
    f = float(focal)
    uv, active = np.asarray(uv, np.float64), np.asarray(active, bool)
    centre, s2 = np.asarray(centre, np.float64)[:, None], float(loss_scale) ** 2
    p, v = np.nonzero(active)                          # the observations, sorted by point
    if len(p) == 0:
        return BundleResult(R, t, f, X, 0.0, 0)
    problem = _Adjustment(p, v, uv, centre, s2, R.shape[0], X.shape[0], t,
                          fixed_view=fixed_view, scale_view=scale_view, refine_focal=refine_focal)
    cost, state = problem.residuals(R, t, f, X)
    lam, nu, it = 1e-3, 2.0, 0
    for it in range(1, max_iterations + 1):
        eq = problem.normal_equations(R, f, state)
        done = False
        while True:
            new, step = np.inf, problem.damped_step(eq, lam)
            if step is not None:
                dc, dp = step
                R2, t2, f2, X2 = problem.moved(R, t, f, X, dc, dp)
                new, state2 = problem.residuals(R2, t2, f2, X2)
            if new < cost:
                predicted = _predicted_fall(eq, lam, dc, dp)
                rho = (cost - new) / predicted if predicted > 0 else 1.0
                done = (cost - new) < tolerance * cost
                # The residuals of an accepted step are the next step's.
                R, t, f, X, cost, state = R2, t2, f2, X2, new, state2
                lam, nu = _nielsen_damping(lam, rho), 2.0
                break
            lam, nu = lam * nu, 2.0 * nu                               # rejected
            if lam > 1e10:
                break
        if lam > 1e10 or done:
            break
    return BundleResult(R, t, f, X, cost, it)

"""Step 5 of the camera solve: bundle adjustment, the poses, the points and the one shared focal
refined together on the reprojection error of every observation.

Levenberg-Marquardt on the normal equations with the points eliminated (Schur complement: one
3x3 block per point, a dense system the size of the cameras), Cauchy-reweighted so that a wrong
match does not drag the cameras. Written here in numpy because the runtime has no SciPy, and
because ``scipy.optimize.least_squares`` (trust region, sparse Jacobian, LSMR) left the focal
where it started on the same problems (docs/CAMERAS.md, "Bundle adjustment").

Parametrisation: ``cam_from_world`` rotations ``R [V, 3, 3]`` updated on the left (R <- exp(w) R)
and translations ``t [V, 3]``; one focal in pixels with the principal point at the image centre
(square pixels, no distortion). One view is held fixed (the gauge) and one coordinate of another
view's translation (the scale, which the images cannot fix).

``fast_bundle_adjust`` minimises the same cost in the same parameters, with Nielsen's damping
and fewer numpy calls a step: the refinement of a model's cameras runs it (``refine``). The
solve keeps ``bundle_adjust`` as it is, because the teacher store (``iris_train.pseudo_poses``)
holds its results and is rebuilt whenever they could change (docs/CAMERAS.md, "A faster
adjustment for the refinement").
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["BundleResult", "bundle_adjust", "fast_bundle_adjust", "reprojection_errors",
           "project"]

#: A step that lowers the cost by less than this fraction of it ends the adjustment.
RELATIVE_TOLERANCE = 1e-6
#: ``fast_bundle_adjust``: an accepted step divides the damping by at most this much.
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


class _Problem:
    """The observations of one adjustment, flattened: point ``p [n]`` (sorted), view ``v [n]``,
    pixels ``uv [n, 2]``."""

    def __init__(self, uv, active, centre, loss_scale):
        self.p, self.v = np.nonzero(active)
        self.uv = uv[self.p, self.v]
        self.P, self.V = active.shape
        self.starts = np.flatnonzero(np.r_[True, self.p[1:] != self.p[:-1]])
        self.centre = centre
        self.s2 = float(loss_scale) ** 2
        self.in_view = (np.arange(self.V)[:, None] == self.v[None]).astype(np.float64)  # [V, n]
        # Where each observation's [7, 3] block goes in a [V, 7, P, 3] array (per_point_dense).
        self.dense_index = (((self.v[:, None, None] * 7 + np.arange(7)[None, :, None]) * self.P
                             + self.p[:, None, None]) * 3 + np.arange(3)[None, None, :]).ravel()

    def per_point_dense(self, x):
        """x [n, 7, 3] per observation -> [7V, 3P], zero where a view does not see a point:
        the Schur complement's sum over points (a point seen by views i and j couples cameras
        i and j) is then one matrix product."""
        out = np.zeros(self.V * 7 * self.P * 3)
        out[self.dense_index] = x.ravel()
        return out.reshape(7 * self.V, 3 * self.P)

    def camera_coords(self, R, t, X):
        """Y [n, 3]: each observed point in its observing camera."""
        return np.matmul(X[None], R.transpose(0, 2, 1))[self.v, self.p] + t[self.v]

    def residuals(self, R, t, f, X):
        Y = self.camera_coords(R, t, X)
        z = np.where(Y[:, 2] > 1e-12, Y[:, 2], 1e-12)
        return f * Y[:, :2] / z[:, None] + self.centre - self.uv, Y

    def cost(self, R, t, f, X) -> float:
        r, Y = self.residuals(R, t, f, X)
        if (Y[:, 2] <= 0).any() or not f > 0:
            return np.inf
        return float(0.5 * self.s2 * np.log1p((r * r).sum(1) / self.s2).sum())   # Cauchy

    def per_view(self, x):
        """Sum of x [n, ...] per view -> [V, ...] (a product with the views' indicator)."""
        return (self.in_view @ x.reshape(len(x), -1)).reshape((self.V,) + x.shape[1:])

    def per_point(self, x):
        """Sum of x [n, ...] per point -> [P, ...] (points without observations: 0)."""
        out = np.zeros((self.P,) + x.shape[1:])
        out[self.p[self.starts]] = np.add.reduceat(x, self.starts, axis=0)
        return out


def _jacobians(Y, a, R_v, f):
    """d(pixel)/d(camera: rotation w, translation, focal) [n, 2, 7] and d(pixel)/d(point)
    [n, 2, 3] of observations with camera coordinates Y [n, 3] = a + t (a = R X, the part the
    rotation acts on) in cameras R_v [n, 3, 3]."""
    n = len(Y)
    iz = 1.0 / Y[:, 2]
    JY = np.zeros((n, 2, 3))
    JY[:, 0, 0] = JY[:, 1, 1] = f * iz
    JY[:, 0, 2] = -f * Y[:, 0] * iz * iz
    JY[:, 1, 2] = -f * Y[:, 1] * iz * iz
    minus_skew = np.zeros((n, 3, 3))                       # d(exp(w) a)/dw = -[a]_x
    minus_skew[:, 0, 1], minus_skew[:, 0, 2] = a[:, 2], -a[:, 1]
    minus_skew[:, 1, 0], minus_skew[:, 1, 2] = -a[:, 2], a[:, 0]
    minus_skew[:, 2, 0], minus_skew[:, 2, 1] = a[:, 1], -a[:, 0]
    Jc = np.concatenate([JY @ minus_skew, JY, (Y[:, :2] * iz[:, None])[:, :, None]], axis=2)
    return Jc, JY @ R_v


def _inverse_factor(A):
    """``Q [P, 3, 3]`` lower triangular with ``A^-1 = Q^T Q`` for symmetric positive definite
    3x3 matrices ``A [P, 3, 3]``: the inverse of their Cholesky factor (A = L L^T, Q = L^-1),
    written out. One vectorised pass where ``np.linalg.inv`` calls LAPACK once per matrix
    (several times slower here); Cholesky is backward stable, so a far point's block, whose
    depth is barely observed, is inverted as accurately as LAPACK does it (cofactors are not:
    they lose the square of the condition)."""
    a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, g = A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]
    l00 = np.sqrt(a)
    l10, l20 = b / l00, c / l00
    l11 = np.sqrt(d - l10 * l10)
    l21 = (e - l20 * l10) / l11
    l22 = np.sqrt(g - l20 * l20 - l21 * l21)
    Q = np.zeros_like(A)
    Q[:, 0, 0], Q[:, 1, 1], Q[:, 2, 2] = 1.0 / l00, 1.0 / l11, 1.0 / l22
    Q[:, 1, 0] = -l10 * Q[:, 0, 0] * Q[:, 1, 1]
    Q[:, 2, 1] = -l21 * Q[:, 1, 1] * Q[:, 2, 2]
    Q[:, 2, 0] = -(l20 * Q[:, 0, 0] + l21 * Q[:, 1, 0]) * Q[:, 2, 2]
    return Q


def bundle_adjust(R, t, focal, centre, points, uv, active, *, fixed_view: int, scale_view: int,
                  refine_focal: bool = True, loss_scale: float = 1.0,
                  max_iterations: int = 50,
                  tolerance: float = RELATIVE_TOLERANCE) -> BundleResult:
    """Refine ``R [V, 3, 3]``, ``t [V, 3]`` (cam_from_world), ``focal`` (pixels; principal point
    ``centre`` [2]) and ``points [P, 3]`` on the observations ``uv [P, V, 2]`` where ``active
    [P, V]`` is True. View ``fixed_view`` does not move; the largest coordinate of view
    ``scale_view``'s translation does not either. ``loss_scale``: the Cauchy scale in pixels.
    Stops after ``max_iterations``, or at the first step that lowers the cost by less than
    ``tolerance`` of it."""
    R, t, X = np.array(R, np.float64), np.array(t, np.float64), np.array(points, np.float64)
    f = float(focal)
    prob = _Problem(np.asarray(uv, np.float64), np.asarray(active, bool),
                    np.asarray(centre, np.float64), loss_scale)
    V, P = R.shape[0], X.shape[0]
    if len(prob.p) == 0:
        return BundleResult(R, t, f, X, 0.0, 0)
    # The free entries of each view's 7 (rotation, translation, focal): the pose of every
    # observed view but the fixed one, less the scale view's largest translation coordinate.
    free = np.zeros((V, 7), bool)
    free[np.unique(prob.v), :6] = True
    free[fixed_view] = False
    free[scale_view, 3 + int(np.argmax(np.abs(t[scale_view])))] = False
    # Parameter index of each entry (-1: fixed); the focal, when refined, is one shared last.
    index = -np.ones((V, 7), np.int64)
    index[free] = np.arange(free.sum())
    n_free = int(free.sum())
    if refine_focal:
        index[:, 6] = n_free
        n_free += 1
    # A [7V, k] matrix D of per-view entries -> [n_free, k] over the parameters: the free pose
    # entries' rows (in parameter order), then the focal's (the sum of every view's).
    rows = np.flatnonzero(free.ravel())

    def reduce(D):
        return np.concatenate([D[rows], D[6::7].sum(0, keepdims=True)]) if refine_focal \
            else D[rows]

    cost = prob.cost(R, t, f, X)
    lam, it = 1e-3, 0
    for it in range(1, max_iterations + 1):
        r, Y = prob.residuals(R, t, f, X)
        w = 1.0 / (1.0 + (r * r).sum(1) / prob.s2)                          # Cauchy IRLS weights
        Jc, Jp = _jacobians(Y, Y - t[prob.v], R[prob.v], f)
        JcT_w = Jc.transpose(0, 2, 1) * w[:, None, None]                    # [n, 7, 2]
        JpT_w = Jp.transpose(0, 2, 1) * w[:, None, None]                    # [n, 3, 2]
        U7 = prob.per_view(JcT_w @ Jc)                                      # [V, 7, 7]
        g7 = prob.per_view((JcT_w @ r[:, :, None])[:, :, 0])                # [V, 7]
        Vp = prob.per_point(JpT_w @ Jp)                                     # [P, 3, 3]
        gp = prob.per_point((JpT_w @ r[:, :, None])[:, :, 0])               # [P, 3]
        Wo = JcT_w @ Jp                                                     # [n, 7, 3]
        U = np.zeros((7 * V, 7 * V))
        for v in range(V):
            U[7 * v:7 * v + 7, 7 * v:7 * v + 7] = U7[v]
        Ur, gr = reduce(reduce(U).T), reduce(g7.reshape(-1, 1))[:, 0]       # U is symmetric
        W = reduce(prob.per_point_dense(Wo))                                # [n_free, 3P]
        done = False
        while True:
            # Schur complement W V^-1 W^T = G G^T with G = W Q^T (V^-1 = Q^T Q per point):
            # one symmetric product (numpy computes a @ a.T as such), half a general one.
            Q = _inverse_factor(Vp + lam * Vp * np.eye(3) + 1e-9 * np.eye(3))
            G = reduce(prob.per_point_dense(Wo @ Q[prob.p].transpose(0, 2, 1)))
            S = Ur + lam * np.diag(np.diag(Ur)) - G @ G.T
            Vinv = Q.transpose(0, 2, 1) @ Q                                 # [P, 3, 3]
            rhs = gr - W @ (Vinv @ gp[:, :, None]).ravel()
            try:
                dc = -np.linalg.solve(S + 1e-12 * np.eye(n_free), rhs)
            except np.linalg.LinAlgError:
                dc = np.full(len(S), np.nan)
            if np.all(np.isfinite(dc)):
                d7 = np.append(dc, 0.0)[index]                      # [V, 7], 0 where fixed
                WTd = (W.T @ dc).reshape(P, 3)
                dp = -(Vinv @ (gp + WTd)[:, :, None])[:, :, 0]
                R2 = np.stack([cv2.Rodrigues(d7[v, :3])[0] @ R[v] for v in range(V)])
                t2, f2, X2 = t + d7[:, 3:6], f + d7[0, 6], X + dp
                new = prob.cost(R2, t2, f2, X2)
                if new < cost:
                    done = (cost - new) < tolerance * cost
                    R, t, f, X, cost = R2, t2, f2, X2, new
                    lam = max(lam / 10.0, 1e-10)
                    break
            lam *= 10.0
            if lam > 1e10:
                break
        if lam > 1e10 or done:
            break
    return BundleResult(R, t, f, X, cost, it)


def _exp_so3(w: np.ndarray) -> np.ndarray:
    """exp([w]_x) [V, 3, 3] of rotation vectors w [V, 3] (Rodrigues' formula)."""
    theta = np.linalg.norm(w, axis=1)
    k = w / np.where(theta > 0, theta, 1.0)[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    return (np.eye(3) + np.sin(theta)[:, None, None] * K
            + (1.0 - np.cos(theta))[:, None, None] * (K @ K))


def fast_bundle_adjust(R, t, focal, centre, points, uv, active, *, fixed_view: int,
                       scale_view: int, refine_focal: bool = True, loss_scale: float = 1.0,
                       max_iterations: int = 50,
                       tolerance: float = RELATIVE_TOLERANCE) -> BundleResult:
    """``bundle_adjust``'s problem, arguments and result, solved with fewer rejected steps and
    less work a step.

    - Nielsen's damping (Madsen, Nielsen & Tingleff, "Methods for non-linear least squares
      problems", 2004): after an accepted step the damping follows the ratio of the cost's fall
      to the fall the linear model predicted, falling at most ``MAX_DAMPING_FALL`` times; after
      a rejected one it grows 2, 4, 8... times. ``bundle_adjust`` divides it by 10 after every
      accepted step and multiplies it by 10 after every rejected one, and each rejected step
      costs a Schur complement and a cost for nothing.
    - Each observation's camera Jacobian in closed form, the cameras' coordinates of the observed
      points from one [P, 3] x [3, 3V] product, the step's rotations in one vectorised
      Rodrigues formula, the Schur complement's sum over points as one product of a [3P, 7V]
      matrix with itself, reduced to the free parameters by a [7V, n_free] selection matrix.

    It ends where ``bundle_adjust`` ends on a well-posed problem (tests/test_cameras.py); on the
    refinement's problems it takes other steps, so it can end in another local minimum where
    the cost has several."""
    R, t, X = np.array(R, np.float64), np.array(t, np.float64), np.array(points, np.float64)
    f = float(focal)
    uv, active = np.asarray(uv, np.float64), np.asarray(active, bool)
    centre, s2 = np.asarray(centre, np.float64), float(loss_scale) ** 2
    V, P = R.shape[0], X.shape[0]
    p, v = np.nonzero(active)                          # the observations, sorted by point
    n = len(p)
    if n == 0:
        return BundleResult(R, t, f, X, 0.0, 0)
    uv = uv[p, v]
    starts = np.flatnonzero(np.r_[True, p[1:] != p[:-1]])
    in_view = (np.arange(V)[:, None] == v[None]).astype(np.float64)     # [V, n]
    # Where each observation's R_v X_p lies in X @ R.reshape(3V, 3).T, [P, 3V] flattened.
    coords = (p * 3 * V + 3 * v)[:, None] + np.arange(3)

    # The free entries of the per-view (rotation, translation, focal) as in bundle_adjust, and
    # T [7V, n_free]: per-view entries from the parameters (the focal shared by every view).
    free = np.zeros((V, 7), bool)
    free[np.unique(v), :6] = True
    free[fixed_view] = False
    free[scale_view, 3 + int(np.argmax(np.abs(t[scale_view])))] = False
    n_pose = int(free.sum())
    T = np.zeros((7 * V, n_pose + int(refine_focal)))
    T[np.flatnonzero(free.ravel()), np.arange(n_pose)] = 1.0
    if refine_focal:
        T[6::7, n_pose] = 1.0
    # M [3P, 7V]: Q_p W_p^T per point (V_p^-1 = Q_p^T Q_p), zero where a view does not see the
    # point, written through the flat index of each observation's [3, 7] block.
    M = np.zeros((3 * P, 7 * V))
    blocks = ((p[:, None, None] * 3 + np.arange(3)[:, None]) * 7 * V
              + (v * 7)[:, None, None] + np.arange(7)).ravel()

    def per_view(x):
        return (in_view @ x.reshape(n, -1)).reshape((V,) + x.shape[1:])

    def per_point(x):
        out = np.zeros((P,) + x.shape[1:])
        out[p[starts]] = np.add.reduceat(x, starts, axis=0)
        return out

    def observed(R, t, X):
        """Y [n, 3]: each observed point in its camera, and a = R_v X_p (Y = a + t_v)."""
        a = (X @ R.reshape(3 * V, 3).T).ravel()[coords]
        return a + t[v], a

    def cost_of(R, t, f, X) -> float:
        Y, _ = observed(R, t, X)
        if (Y[:, 2] <= 0).any() or not f > 0:
            return np.inf
        r = f * Y[:, :2] / Y[:, 2:] + centre - uv
        return float(0.5 * s2 * np.log1p((r * r).sum(1) / s2).sum())             # Cauchy

    cost = cost_of(R, t, f, X)
    lam, nu, it = 1e-3, 2.0, 0
    for it in range(1, max_iterations + 1):
        Y, a = observed(R, t, X)
        iz = 1.0 / np.where(Y[:, 2] > 1e-12, Y[:, 2], 1e-12)
        r = f * Y[:, :2] * iz[:, None] + centre - uv
        w = 1.0 / (1.0 + (r * r).sum(1) / s2)                            # Cauchy IRLS weights
        # d(pixel)/dY = [[fz, 0, gx], [0, fz, gy]]; the rotation's columns are its product with
        # d(exp(w) a)/dw = -[a]_x, the point's with R_v.
        fz = f * iz
        gx, gy = -Y[:, 0] * fz * iz, -Y[:, 1] * fz * iz
        Jc = np.zeros((n, 2, 7))
        Jc[:, 0, 0], Jc[:, 0, 1], Jc[:, 0, 2] = gx * a[:, 1], fz * a[:, 2] - gx * a[:, 0], \
            -fz * a[:, 1]
        Jc[:, 1, 0], Jc[:, 1, 1], Jc[:, 1, 2] = gy * a[:, 1] - fz * a[:, 2], -gy * a[:, 0], \
            fz * a[:, 0]
        Jc[:, 0, 3], Jc[:, 0, 5], Jc[:, 1, 4], Jc[:, 1, 5] = fz, gx, fz, gy
        Jc[:, :, 6] = Y[:, :2] * iz[:, None]
        Rv = R[v]
        Jp = np.stack([fz[:, None] * Rv[:, 0] + gx[:, None] * Rv[:, 2],
                       fz[:, None] * Rv[:, 1] + gy[:, None] * Rv[:, 2]], axis=1)    # [n, 2, 3]
        JcT_w = Jc.transpose(0, 2, 1) * w[:, None, None]
        JpT_w = Jp.transpose(0, 2, 1) * w[:, None, None]
        U = np.zeros((V, 7, V, 7))
        U[np.arange(V), :, np.arange(V)] = per_view(JcT_w @ Jc)
        Ur = T.T @ U.reshape(7 * V, 7 * V) @ T
        gr = T.T @ per_view((JcT_w @ r[:, :, None])[:, :, 0]).ravel()
        Vp = per_point(JpT_w @ Jp)                                            # [P, 3, 3]
        gp = per_point((JpT_w @ r[:, :, None])[:, :, 0])                      # [P, 3]
        Wo = JcT_w @ Jp                                                       # [n, 7, 3]
        WoT = Wo.transpose(0, 2, 1)
        diag_U, diag_V = np.diag(Ur), np.diagonal(Vp, axis1=1, axis2=2)
        done = False
        while True:
            Q = _inverse_factor(Vp + lam * diag_V[:, :, None] * np.eye(3) + 1e-9 * np.eye(3))
            M.reshape(-1)[blocks] = (Q[p] @ WoT).ravel()
            S = Ur + lam * np.diag(diag_U) - T.T @ (M.T @ M) @ T
            Vinv = Q.transpose(0, 2, 1) @ Q                                   # [P, 3, 3]
            y = (Vinv @ gp[:, :, None])[:, :, 0]
            rhs = gr - T.T @ per_view((Wo @ y[p][:, :, None])[:, :, 0]).ravel()
            try:
                dc = -np.linalg.solve(S + 1e-12 * np.eye(len(S)), rhs)
            except np.linalg.LinAlgError:
                dc = np.full(len(S), np.nan)
            new = np.inf
            if np.all(np.isfinite(dc)):
                d7 = (T @ dc).reshape(V, 7)                       # 0 where fixed
                WTd = per_point((WoT @ d7[v][:, :, None])[:, :, 0])
                dp = -(Vinv @ (gp + WTd)[:, :, None])[:, :, 0]
                R2, t2, f2, X2 = _exp_so3(d7[:, :3]) @ R, t + d7[:, 3:6], f + d7[0, 6], X + dp
                new = cost_of(R2, t2, f2, X2)
            if new < cost:
                # The fall the damped linear model predicts: (dx^T (lam D dx - g)) / 2.
                predicted = 0.5 * (lam * (diag_U @ dc**2 + (diag_V * dp**2).sum())
                                   - gr @ dc - (gp * dp).sum())
                rho = (cost - new) / predicted if predicted > 0 else 1.0
                done = (cost - new) < tolerance * cost
                R, t, f, X, cost = R2, t2, f2, X2, new
                fall = max(1.0 / MAX_DAMPING_FALL, 1.0 - (2.0 * rho - 1.0) ** 3)
                lam, nu = max(lam * fall, 1e-10), 2.0
                break
            lam, nu = lam * nu, 2.0 * nu
            if lam > 1e10:
                break
        if lam > 1e10 or done:
            break
    return BundleResult(R, t, f, X, cost, it)

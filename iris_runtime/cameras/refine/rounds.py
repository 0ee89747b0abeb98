"""The refinement's bundle adjustment: rounds of ``bundle.bundle_adjust`` from a start.

A start's cameras get a point per track triangulated on them (``start_adjustment``), then rounds
(``run_rounds``): each adjusts the points seen twice, drops the observations that reproject too
far or land behind a camera, and triangulates again the points left with fewer than two
(``adjust_round``). The first round holds the focal: a pose error of several degrees moves the
focal as much as a wrong focal does.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..bundle import bundle_adjust, reprojection_errors
from ..mapper import Reconstruction
from ..solve import LOCATE_MIN_INLIERS
from ..triangulation import triangulate

__all__ = ["AdjustOptions", "Adjustment", "start_adjustment", "adjust_round", "run_rounds",
           "as_reconstruction"]


@dataclass(frozen=True)
class AdjustOptions:
    """The rounds of the adjustment.

    rounds:                 (Levenberg-Marquardt iterations, whether the focal moves) per round.
    tolerance:              a round ends early at a step that lowers the cost by less than this
                            share of it (the solve's adjustments go on to
                            ``bundle.RELATIVE_TOLERANCE``, a hundredth of this): the rounds of
                            every start are the refinement's largest cost.
    choose_after:           rounds every start runs before the best is chosen; the others run
                            the rest only while no start has confirmed the best.
    retriangulation_angle:  points dropped by a round (but the last) are triangulated again
                            where seen under this angle (degrees) or more.
    min_observations:       a view counts as refined ("solved") with this many observations left
                            after the last round; the others are reported "unposed" (the caller
                            keeps the model's camera for them).
    """
    rounds: tuple[tuple[int, bool], ...] = ((20, False), (50, True))
    tolerance: float = 1e-4
    choose_after: int = 1
    retriangulation_angle: float = 0.5
    min_observations: int = LOCATE_MIN_INLIERS


@dataclass
class Adjustment:
    """One start's state: cam_from_world ``R [V, 3, 3]``, ``t [V, 3]``, ``focal``, one point per
    track ``X [T, 3]`` and the observations it keeps, ``active [T, V]``."""
    R: np.ndarray
    t: np.ndarray
    focal: float
    X: np.ndarray
    active: np.ndarray


def start_adjustment(R, t, f, centre, tracks, views=None) -> Adjustment:
    """The adjustment of cameras ``R, t, f`` with every track seen by ``views`` (bool [V];
    None: all) triangulated on them."""
    observed = tracks.observed if views is None else tracks.observed & views[None]
    X, ok = triangulate(R, t, f, centre, tracks.uv, observed, max_error=np.inf, min_angle=0.0)
    return Adjustment(R, t, f, X, observed & ok[:, None])


def adjust_round(a: Adjustment, iterations: int, refine_focal: bool, last: bool, centre, tracks,
                 scale_view: int, max_error: float, loss_scale: float,
                 options: AdjustOptions) -> Adjustment | None:
    """One round of the adjustment: bundle-adjust the points seen twice, drop observations
    beyond ``max_error`` or behind a camera, and (unless ``last``) triangulate the points left
    with fewer than two again; None when the focal left the positive numbers."""
    keep = a.active.sum(1) >= 2
    res = bundle_adjust(a.R, a.t, a.focal, centre, a.X[keep], tracks.uv[keep], a.active[keep],
                        fixed_view=0, scale_view=scale_view, refine_focal=refine_focal,
                        loss_scale=loss_scale, max_iterations=iterations,
                        tolerance=options.tolerance)
    if not (np.isfinite(res.focal) and res.focal > 0):
        return None
    X = a.X.copy()
    X[keep] = res.points
    err, z = reprojection_errors(res.R, res.t, res.focal, centre, X, tracks.uv)
    active = a.active & (err <= max_error) & (z > 0)
    if not last:
        # Only the points left with fewer than two observations are replaced (each track is
        # triangulated on its own, so the others' need not be computed).
        todo = np.flatnonzero((active.sum(1) < 2) & (tracks.observed.sum(1) >= 2))
        X2, ok2 = triangulate(res.R, res.t, res.focal, centre, tracks.uv[todo],
                              tracks.observed[todo], max_error=max_error,
                              min_angle=options.retriangulation_angle)
        again = todo[ok2]
        X[again], active[again] = X2[ok2], tracks.observed[again]
    else:
        active &= (active.sum(1) >= 2)[:, None]
    return Adjustment(res.R, res.t, res.focal, X, active)


def run_rounds(a: Adjustment | None, first: int, end: int | None, centre, tracks,
               scale_view: int, max_error: float, loss_scale: float,
               options: AdjustOptions) -> Adjustment | None:
    """Rounds ``first`` up to ``end`` (None: the last) of ``options.rounds`` run on ``a``;
    None once a round fails."""
    last = len(options.rounds) - 1
    for n, (iterations, refine_focal) in enumerate(options.rounds[:end]):
        if n >= first:
            a = adjust_round(a, iterations, refine_focal, n == last, centre, tracks, scale_view,
                             max_error, loss_scale, options) if a else None
    return a


def as_reconstruction(a: Adjustment, tracks, scale_view: int,
                      options: AdjustOptions) -> Reconstruction:
    """The adjustment as the mapper's ``Reconstruction`` (a view counts as registered with
    ``options.min_observations`` observations)."""
    return Reconstruction(a.R, a.t, a.focal, a.active.sum(0) >= options.min_observations, a.X,
                          a.active.sum(1) >= 2, tracks.observed & ~a.active, (0, scale_view))

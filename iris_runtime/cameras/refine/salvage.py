"""Stage 3 of the refinement: where no start confirms the best one, keep the views one agrees on.

The largest set of views on which another start agrees with the best pair by pair
(``salvage_core``) is kept when it is large enough; the other views, whose poses in the best
start nothing confirmed, are posed against the kept views' points by PnP RANSAC as the mapper
registers a view, and the adjustment's rounds run again (``salvage_agreed_views``;
docs/CAMERAS.md, "Salvaging the views two starts agree on").
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np

from ..locate import PNP_MIN_INLIERS, pose_from_points
from ..mapper import MapperOptions, Reconstruction
from ..triangulation import triangulate
from . import confirm, rounds
from .confirm import AgreementOptions
from .pairs import Evidence

__all__ = ["CappedPnP", "SalvageOptions", "SalvageStages", "salvage_core",
           "salvage_agreed_views"]


@dataclass(frozen=True)
class CappedPnP:
    """The PnP RANSAC that poses the views a salvage did not keep, and the witness mapping's
    registrations: cheaper than the solve's, for the same poses.

    method:         OpenCV's PnP on the RANSAC's samples: AP3P on four points (the solve's
                    SQPnP made the views with few inliers, which run all of the RANSAC's
                    iterations, slower, to the same cameras).
    max_iterations: the RANSAC's iterations at most (the solve's: ``locate.PNP_ITERATIONS``,
                    1000); it also stops once a pose would have been drawn with its confidence
                    (``locate.confident_iterations``). By this cap a pose that 42% of a view's
                    correspondences support would have been drawn with that confidence: only
                    the views few correspondences support need more.
    """
    method: int = cv2.SOLVEPNP_AP3P
    max_iterations: int = 300


@dataclass(frozen=True)
class SalvageOptions:
    """When a set of agreeing views is kept.

    min_core_share: the kept views must be this share of the views or more (half: the majority
                    the scene's points then come from) ...
    min_core_views: ... and this many or more (three-view sets ended worse than the solve).
    pnp:            how the other views are posed against the kept views' points.
    """
    min_core_share: float = 0.5
    min_core_views: int = 4
    pnp: CappedPnP = field(default_factory=CappedPnP)


def salvage_core(best: Reconstruction, witnesses: list[Reconstruction],
                 options: SalvageOptions = SalvageOptions(),
                 agreement: confirm.AgreementOptions = confirm.AgreementOptions(),
                 ) -> np.ndarray | None:
    """bool [V]: the largest set of views on which a witness (another start's end) agrees with
    ``best`` pair by pair (``agreeing_views``), or None when it holds fewer than
    ``options.min_core_share`` of the views or ``options.min_core_views``."""
    V = len(best.registered)
    core = np.zeros(V, bool)
    for w in witnesses:
        views = confirm.agreeing_views(confirm.agreeing_pairs(
            best.R, best.t, best.registered, w.R, w.t, w.registered, agreement.degrees))
        if views.sum() > core.sum():
            core = views
    return core if core.sum() >= max(options.min_core_views, options.min_core_share * V) \
        else None


class SalvageStages(Protocol):
    """The stages' options a salvage reads (``ladder.RefineOptions`` has them by these names)."""
    salvage: SalvageOptions
    adjust: rounds.AdjustOptions
    agreement: AgreementOptions


def salvage_agreed_views(best: Reconstruction, witnesses: list[Reconstruction],
                         evidence: Evidence, opts: MapperOptions,
                         stages: SalvageStages) -> Reconstruction | None:
    """Where no start confirms the ``best`` one: its views in ``salvage_core`` are kept, their
    points triangulated again from those views alone, the other views posed against them by PnP
    RANSAC as the mapper registers a view (their poses in ``best`` are what no witness
    confirmed), and the refinement's rounds run again. None when there is no such set, or view
    0 (the gauge) is not posed. ``opts`` in the photos' pixels."""
    options, adjust = stages.salvage, stages.adjust
    core = salvage_core(best, witnesses, options, stages.agreement)
    if core is None:
        return None
    tracks, centre = evidence.tracks, evidence.centre
    R, t, f = best.R.copy(), best.t.copy(), best.focal
    X, ok = triangulate(R, t, f, centre, tracks.uv, tracks.observed & core[None],
                        max_error=opts.max_error, min_angle=adjust.retriangulation_angle)
    posed = core.copy()
    for v in np.flatnonzero(~core):
        sees = ok & tracks.observed[:, v]
        pose = pose_from_points(X[sees], tracks.uv[sees, v], f, evidence.image_size,
                                max_error=opts.pnp_error, min_inliers=PNP_MIN_INLIERS,
                                method=options.pnp.method, confident_stop=True,
                                max_iterations=options.pnp.max_iterations)
        if pose is not None:
            R[v], t[v] = pose[0], pose[1]
            posed[v] = True
    if not posed[0]:
        return None
    # The scale gauge on a posed view (the one farthest from view 0).
    C = -np.einsum("vji,vj->vi", R, t)
    scale_view = int(np.argmax(np.where(posed, np.linalg.norm(C - C[0], axis=1), -1.0)))
    a = rounds.start_adjustment(R, t, f, centre, tracks, posed)
    a = rounds.run_rounds(a, 0, None, centre, tracks, scale_view, opts.max_error,
                          opts.loss_scale, adjust)
    return rounds.as_reconstruction(a, tracks, scale_view, adjust) if a is not None else None

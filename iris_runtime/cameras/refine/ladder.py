"""The refinement's entry point, ``refine_cameras``, and its ladder of decisions.

1. ``starts.ranked_starts``: every start adjusted; the best-ranked is the candidate.
2. ``confirm.confirming_start``: another start agrees with it -> kept.
3. ``salvage.salvage_agreed_views``: else the views another start agrees on -> kept, the others
   posed against them.
4. ``witness.witness_mapping`` and ``witness.witness_verdict``: else a mapping of the pairs
   confirms a start -> kept, or agrees with the best on enough views -> salvaged.
5. Else None: the caller runs the solve.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..features import canonical_order
from ..mapper import MapperOptions, Reconstruction
from ..solve import CameraSolve, check_depth_range, check_photos, finish_solve
from . import confirm, salvage, starts, witness
from .pairs import Evidence, PairOptions, check_start, read_pairs
from .rounds import AdjustOptions

__all__ = ["RefineOptions", "DEFAULTS", "refine_cameras"]


@dataclass(frozen=True)
class RefineOptions:
    """The refinement's settings, one group per stage; the defaults are the shipped ones
    (the measurements behind them: docs/CAMERAS.md and docs/record/cameras-refactor.md)."""
    pairs: PairOptions = field(default_factory=PairOptions)
    starts: starts.StartOptions = field(default_factory=starts.StartOptions)
    adjust: AdjustOptions = field(default_factory=AdjustOptions)
    agreement: confirm.AgreementOptions = field(default_factory=confirm.AgreementOptions)
    salvage: salvage.SalvageOptions = field(default_factory=salvage.SalvageOptions)
    witness: witness.WitnessOptions = field(default_factory=witness.WitnessOptions)


#: The settings ``refine_cameras`` runs with when given none: ``RefineOptions()``, which a study
#: may replace (``scripts/camera_study.py --set refine.STAGE.FIELD=VALUE``).
DEFAULTS = RefineOptions()


def refine_cameras(photos, world_from_cam, focal: float, depth_range: tuple[float, float], *,
                   options: MapperOptions | None = None,
                   refinement: RefineOptions | None = None) -> CameraSolve | None:
    """The cameras of ``photos`` (V uint8 photos of one size, RGB [H, W, 3] or grey [H, W]),
    refined from a model's: ``world_from_cam [V, 4, 4]`` (rigid, any frame and unit) and
    ``focal`` (pixels of the photos). Returns a ``CameraSolve`` in the renderer's
    ``depth_range`` as ``solve_cameras`` does (views left with fewer than
    ``AdjustOptions.min_observations`` observations "unposed"), or None when the photos do not
    constrain the cameras (fewer than two views refined, a start without a baseline, an
    adjustment that left the focal non-positive) or when no stage of the ladder keeps a
    start (a wrong minimum, or a scene the photos leave ambiguous).
    ``options``: the mapper's thresholds (pixels at ``two_view.REFERENCE_SIZE``): the
    adjustment uses ``max_error`` and ``loss_scale``, the ranking of the starts ``max_error``,
    the salvage ``pnp_error``, the witness mapping all of them. ``refinement``: the stages'
    settings (default ``DEFAULTS``)."""
    photos = check_photos(photos)
    near, far = check_depth_range(depth_range)
    V = len(photos)
    start, focal = check_start(world_from_cam, focal, V)
    options = options or MapperOptions()
    stages = refinement or DEFAULTS
    # As the solve: the photos in canonical_order, so that their order only decides the root.
    perm = canonical_order(photos)
    # ... and the start in the frame of canonical view 0 (the adjustment's gauge), so that the
    # same cameras given in another frame start the same adjustment: a round that ends at its
    # tolerance ends where it would have in any frame.
    start = np.linalg.inv(start[perm[0]]) @ start[perm]
    # The scale gauge: one coordinate of the view farthest from view 0 stays where it starts.
    baseline = np.linalg.norm(start[:, :3, 3] - start[0, :3, 3], axis=1)
    scale_view = int(np.argmax(baseline))
    if V < 2 or not baseline[scale_view] > 1e-9 * max(1.0, np.abs(start[:, :3, 3]).max()):
        return None
    evidence = read_pairs([photos[v] for v in perm], focal, stages.pairs)
    opts = options.in_pixels(evidence.px)    # the thresholds in these photos' pixels
    best = _climb(evidence, start, scale_view, opts, stages)
    if best is None:
        return None
    refined = best.registered                                      # canonical numbering
    cams = np.full((V, 4, 4), np.nan)
    cams[refined] = np.eye(4)
    cams[refined, :3, :3], cams[refined, :3, 3] = best.R[refined], best.t[refined]
    status = np.array(["unposed"] * V, dtype=object)
    status[perm[refined]] = "solved"
    return finish_solve(best, evidence.tracks, evidence.features, cams, status, perm, evidence.k,
                        photos[0].shape[:2], (near, far))


def _climb(evidence: Evidence, start: np.ndarray, scale_view: int, opts: MapperOptions,
           stages: RefineOptions) -> Reconstruction | None:
    """The ladder (see the module): the reconstruction kept, or None (the caller runs the
    solve)."""
    ends = starts.ranked_starts(evidence, start, scale_view, opts, stages.starts, stages.adjust)
    best = next(ends, None)
    if best is None or best.registered.sum() < 2:
        return None
    if len(stages.starts.kinds) < 2:                 # nothing could confirm it
        return best
    confirmed, others = confirm.confirming_start(best, ends, stages.agreement)
    if confirmed:
        return best
    kept = salvage.salvage_agreed_views(best, others, evidence, opts, stages)
    if kept is None and stages.witness.trials:
        # A mapping of fewer views than min_core_views salvages nothing, and confirms (on
        # min_share of the pairs) no start that poses more views than it does.
        useful = min(stages.salvage.min_core_views,
                     *(int(r.registered.sum()) for r in [best, *others]))
        mapped = witness.witness_mapping(evidence, best.focal, opts, useful, stages)
        kept = witness.witness_verdict(best, others, mapped, evidence, opts, stages)
    return kept

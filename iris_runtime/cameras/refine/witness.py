"""Stage 4 of the refinement: where no start agrees with the best on enough views, a mapping
decides.

The incremental mapper runs on the refinement's own pairs and tracks at the best start's focal
(``witness_mapping``): its reconstruction owes nothing to the starts' cameras, though it shares
the pairs' essential matrices with two of them. A start it confirms is kept, or the views it
agrees with the best start on are salvaged (``witness_verdict``); otherwise the caller runs the
solve (docs/CAMERAS.md, "A mapping as the witness").
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Protocol

from ..mapper import MapperOptions, Reconstruction, incremental_mapping
from ..two_view import TwoViewGeometry, intrinsics, median_triangulation_angle
from . import confirm, salvage
from .salvage import SalvageStages
from .pairs import Evidence

__all__ = ["WitnessOptions", "witness_mapping", "witness_verdict"]


@dataclass(frozen=True)
class WitnessOptions:
    """The witness mapping.

    trials:     starting pairs the mapper tries (0: no witness, the caller runs the solve).
    iterations: its Levenberg-Marquardt iterations after each registration and at the end
                (the solve's: ``MapperOptions.ba_iterations`` and ``final_ba_iterations``,
                10 and 50): its cameras need only be right to the resolution ``agreement``
                judges them at.
    Its registrations pose views with ``SalvageOptions.pnp``.
    """
    trials: int = 2
    iterations: tuple[int, int] = (5, 20)


class WitnessStages(SalvageStages, Protocol):
    """The stages' options the witness reads (``ladder.RefineOptions`` has them by these names)."""
    witness: WitnessOptions


def witness_mapping(evidence: Evidence, focal: float, opts: MapperOptions, useful_views: int,
                    stages: WitnessStages) -> Reconstruction | None:
    """The incremental mapper's reconstruction of the refinement's tracks (``incremental_mapping``
    at ``focal``, ``WitnessOptions.trials`` starting pairs and ``WitnessOptions.iterations``, PnP
    by ``SalvageOptions.pnp``), started from its pairs' essential matrices: the solve's method
    on data already at hand, without its focal priors, homographies and second pass. A starting pair's mapping that registers fewer than ``useful_views`` views is not
    finished (``MapperOptions.finish_min_views``): the caller can use none such. None when no
    pair starts one. ``opts`` in the photos' pixels."""
    ev, options, pnp = evidence, stages.witness, stages.salvage.pnp
    K = intrinsics(focal, ev.image_size)
    geometries = {}
    for (a, b), m in ev.inliers.items():
        T = ev.relative[a, b][0]
        angle = median_triangulation_angle(ev.features[a].uv[m[:, 0]],
                                           ev.features[b].uv[m[:, 1]], T, K)
        # No homography: every pair counts as "general", scored by its inliers and angle.
        geometries[a, b] = TwoViewGeometry("general", m, 0, T, angle)
    opts = dataclasses.replace(opts, init_trials=options.trials, min_trials=1,
                               ba_iterations=options.iterations[0],
                               final_ba_iterations=options.iterations[1],
                               pnp_method=pnp.method, pnp_confident_stop=True,
                               pnp_iterations=pnp.max_iterations,
                               finish_min_views=useful_views)
    return incremental_mapping(ev.features, ev.tracks, geometries, (focal,), ev.image_size, opts)


def witness_verdict(best: Reconstruction, ends: list[Reconstruction],
                    mapped: Reconstruction | None, evidence: Evidence | None,
                    opts: MapperOptions | None, stages: WitnessStages | None = None,
                    ) -> Reconstruction | None:
    """The first of ``best`` and the other starts' ``ends`` that the witness mapping ``mapped``
    confirms (``confirm.agreement`` on ``AgreementOptions.min_share`` of the pairs either of
    them poses); else ``best`` salvaged on the views ``mapped`` agrees with it on
    (``salvage.salvage_agreed_views``, with ``evidence``, ``opts`` and ``stages``; without
    ``stages`` the verdict alone, no salvage); None when there is no witness or neither holds."""
    if mapped is None:
        return None
    agreement = confirm.AgreementOptions() if stages is None else stages.agreement
    for rec in (best, *ends):
        # Both ways: a start that leaves a view unposed is not confirmed by a witness that
        # poses it, nor a start by a witness that poses fewer of its views.
        if min(confirm.agreement(rec.R, rec.t, rec.registered, mapped.R, mapped.t,
                                 mapped.registered, agreement.degrees),
               confirm.agreement(mapped.R, mapped.t, mapped.registered, rec.R, rec.t,
                                 rec.registered, agreement.degrees)) >= agreement.min_share:
            return rec
    if stages is None:                  # the verdict alone: no stages to salvage with
        return None
    return salvage.salvage_agreed_views(best, [mapped], evidence, opts, stages)

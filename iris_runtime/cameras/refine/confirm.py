"""Stage 2 of the refinement: does another start confirm the best one?

The adjustment can end in a wrong minimum where the head and the pairs are both far off, but it
rarely reaches the same wrong minimum from two starts. So the best start is kept where another
start's cameras agree with it, pair of views by pair of views, on enough of the pairs
(``agreement``; docs/CAMERAS.md, "Telling a wrong refinement"). Two sets of cameras agree on a
pair when its relative rotation and its baseline direction (scale-free, as RPA measures them)
agree within ``AgreementOptions.degrees``.
"""
from __future__ import annotations

import itertools
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ..mapper import Reconstruction
from .starts import rotation_angle

__all__ = ["AgreementOptions", "agreeing_pairs", "agreement", "agreeing_views", "confirms",
           "confirming_start"]


@dataclass(frozen=True)
class AgreementOptions:
    """When two sets of cameras agree.

    min_share: the share of the pairs of views a second set must agree on for the first to count
               as confirmed; under it the refinement is taken to have ended in a wrong minimum.
               Between the shares that starts which both found the scene reach and that a wrong
               minimum reaches (docs/record/cameras-refactor.md).
    degrees:   two sets agree on a pair whose relative rotation and baseline direction agree
               within this angle.
    """
    min_share: float = 2.0 / 3.0
    degrees: float = 5.0


def agreeing_pairs(R_a: np.ndarray, t_a: np.ndarray, posed_a: np.ndarray, R_b: np.ndarray,
                   t_b: np.ndarray, posed_b: np.ndarray,
                   degrees: float = AgreementOptions.degrees) -> np.ndarray:
    """bool [V, V], symmetric: the pairs of views posed in both cameras a and b (cam_from_world
    ``R [V, 3, 3]``, ``t [V, 3]``, ``posed bool [V]``) whose relative rotation and baseline
    direction (scale-free, as RPA measures them) agree within ``degrees``."""
    C_a = -np.einsum("vji,vj->vi", R_a, t_a)
    C_b = -np.einsum("vji,vj->vi", R_b, t_b)
    tolerance = np.radians(degrees)
    V = len(R_a)
    agree = np.zeros((V, V), bool)
    for i in range(V):
        for j in range(i + 1, V):
            if not (posed_a[i] and posed_a[j] and posed_b[i] and posed_b[j]):
                continue
            # Baselines in camera i's frame: the frames of a and b may differ by any similarity.
            d_a, d_b = R_a[i] @ (C_a[j] - C_a[i]), R_b[i] @ (C_b[j] - C_b[i])
            n = np.linalg.norm(d_a) * np.linalg.norm(d_b)
            agree[i, j] = agree[j, i] = bool(
                n > 0 and rotation_angle(R_a[j] @ R_a[i].T, R_b[j] @ R_b[i].T) <= tolerance
                and np.arccos(np.clip(d_a @ d_b / n, -1.0, 1.0)) <= tolerance)
    return agree


def agreement(R_a: np.ndarray, t_a: np.ndarray, posed_a: np.ndarray, R_b: np.ndarray,
              t_b: np.ndarray, posed_b: np.ndarray,
              degrees: float = AgreementOptions.degrees) -> float:
    """The share of the pairs of views posed in cameras a on which cameras b agree
    (``agreeing_pairs``; a pair b leaves unposed disagrees). 0 when a poses fewer than two
    views."""
    i, j = np.triu_indices(len(R_a), 1)
    counted = posed_a[i] & posed_a[j]
    agree = agreeing_pairs(R_a, t_a, posed_a, R_b, t_b, posed_b, degrees)[i, j]
    return float(agree[counted].mean()) if counted.any() else 0.0


def agreeing_views(agree: np.ndarray) -> np.ndarray:
    """bool [V]: the largest set of views every pair of which agrees (``agree`` bool [V, V],
    symmetric, from ``agreeing_pairs``), the one with the lowest view indices among equals: a
    largest clique, by trying the sets largest first (at most 2^V of them; V is a handful)."""
    V = len(agree)
    best = np.zeros(V, bool)
    for n in range(V, 1, -1):
        for views in itertools.combinations(range(V), n):
            if agree[np.ix_(views, views)][np.triu_indices(n, 1)].all():
                best[list(views)] = True
                return best
    return best


def confirms(a: Reconstruction, b: Reconstruction, options: AgreementOptions) -> bool:
    """Whether ``b``'s cameras agree with ``a``'s on ``options.min_share`` of the pairs ``a``
    poses."""
    return agreement(a.R, a.t, a.registered, b.R, b.t, b.registered,
                     options.degrees) >= options.min_share


def confirming_start(best: Reconstruction, others: Iterable[Reconstruction],
                     options: AgreementOptions) -> tuple[bool, list[Reconstruction]]:
    """(whether one of ``others`` confirms ``best``, the others asked): they are asked in turn,
    and no further once one has (``others`` may be lazy: the rest are never adjusted)."""
    asked = []
    for rec in others:
        asked.append(rec)
        if confirms(best, rec, options):
            return True, asked
    return False, asked

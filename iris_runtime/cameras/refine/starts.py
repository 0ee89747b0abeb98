"""Stage 1 of the refinement: the starts, and which of them is best.

Each start is a set of cameras the adjustment begins at (``start_cameras``): the model's
("model"), the model's centres turned by the pairs' rotations (the pairs' essential matrices'
rotations averaged, ``average_rotations``: "rotations"), and the pairs' rotations with the
centres their translation directions give (``average_centres``: "pairs", which needs nothing of
the model but its focal). A head a few degrees off starts well from its own cameras; where it
has not learned a scene's rotations, or its centres, the pairs' do better (docs/CAMERAS.md,
"Refining the model's cameras"). Every start runs the first rounds of the adjustment
(``rounds``); ``ranked_starts`` then ranks them as the mapper ranks reconstructions (the most
views registered, then ``mapper.reprojection_score``) and finishes them lazily, best first.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ...validation import nearest_rotation
from ..mapper import MapperOptions, Reconstruction, reprojection_score
from . import rounds
from .pairs import Evidence

__all__ = ["StartOptions", "average_rotations", "average_centres", "start_cameras",
           "ranked_starts", "rotation_angle"]


@dataclass(frozen=True)
class StartOptions:
    """The starts.

    kinds:            the starts tried, of "model", "rotations" and "pairs" (see the module);
                      with one, nothing can confirm it and the ladder stops at it.
    averaging_rounds: reweighting rounds of the rotation averaging: each weighs a pair down by
                      its residual angle, so that one wrong pair does not drag the others.
    averaging_scale:  the Cauchy scale of that reweighting (degrees): a pair this far off
                      counts half.
    """
    kinds: tuple[str, ...] = ("model", "rotations", "pairs")
    averaging_rounds: int = 4
    averaging_scale: float = 5.0


def rotation_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The angle (radians) of the rotation between ``Ra`` and ``Rb`` [3, 3]."""
    return float(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1.0) / 2.0, -1.0, 1.0)))


def average_rotations(relative: dict[tuple[int, int], tuple[np.ndarray, float]],
                      R_start: np.ndarray, options: StartOptions = StartOptions()) -> np.ndarray:
    """Rotations ``R [V, 3, 3]`` (cam_from_world) that agree best with the pairs' relative
    rotations ``relative {(a, b): (R_ab [3, 3] cam_b_from_cam_a, weight)}``: chordal L2
    averaging (the top three eigenvectors of the block matrix of the pairs, each block projected
    onto SO(3)), reweighted ``averaging_rounds`` times by the pairs' residual angles (Cauchy,
    ``averaging_scale`` degrees) so that a wrong pair does not drag the others. View 0 keeps
    ``R_start[0]``; views no pair links to view 0 keep ``R_start``'s."""
    V = len(R_start)
    linked, grew = {0}, True
    while grew:
        grew = False
        for a, b in relative:
            if (a in linked) != (b in linked):
                linked |= {a, b}
                grew = True
    views = sorted(linked)
    pos = {v: k for k, v in enumerate(views)}
    pairs = [(pos[a], pos[b], R_ab, w) for (a, b), (R_ab, w) in relative.items()
             if a in pos and b in pos]
    out = R_start.copy()
    if len(views) < 2:
        return out
    weights = np.array([w for *_, w in pairs], np.float64)
    for _ in range(options.averaging_rounds):
        G = np.zeros((3 * len(views), 3 * len(views)))
        for (i, j, R_ij, _), w in zip(pairs, weights):
            G[3 * j:3 * j + 3, 3 * i:3 * i + 3] += w * R_ij
            G[3 * i:3 * i + 3, 3 * j:3 * j + 3] += w * R_ij.T
        X = np.linalg.eigh(G)[1][:, -3:].reshape(len(views), 3, 3)
        Q = nearest_rotation(X @ np.linalg.inv(X[0]))             # view k from view 0
        residual = np.array([np.degrees(rotation_angle(Q[j] @ Q[i].T, R_ij))
                             for i, j, R_ij, _ in pairs])
        weights = np.array([w for *_, w in pairs]) / (
            1.0 + (residual / options.averaging_scale) ** 2)
    out[views] = Q @ R_start[0]
    return out


def average_centres(relative: dict[tuple[int, int], tuple[np.ndarray, float]], R: np.ndarray,
                    start: np.ndarray) -> np.ndarray:
    """Camera centres ``[V, 3]`` whose baselines point along the pairs' translation directions
    (``relative {(a, b): (cam_b_from_cam_a [4, 4] (unit translation), weight)}``, rotations
    ``R [V, 3, 3]`` cam_from_world): the least-squares null vector of d_ab x (c_a - c_b) = 0
    with c_0 fixed at ``start [V, 3]``'s, scaled (and signed) to agree best with ``start``'s
    centres; ``start`` itself where the directions leave more than that scale free."""
    V = len(R)
    rows = []
    for (a, b), (T, w) in relative.items():
        d = R[b].T @ T[:3, 3]                         # c_a - c_b, in the world frame
        cross = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
        A = np.zeros((3, 3 * V))
        A[:, 3 * a:3 * a + 3], A[:, 3 * b:3 * b + 3] = cross, -cross
        rows.append(np.sqrt(w) * A)
    if not rows:
        return start
    A = np.concatenate(rows)[:, 3:]                   # c_0 is fixed
    if A.shape[0] < A.shape[1]:
        return start
    _, sv, Vt = np.linalg.svd(A)
    if sv[-2] < 1e-9 * sv[0]:
        return start
    c = np.concatenate([np.zeros(3), Vt[-1]]).reshape(V, 3)
    rel = start - start[0]
    return start[0] + c * (np.sum(c * rel) / max(np.sum(c * c), 1e-300))


def start_cameras(kind: str, relative: dict, R0: np.ndarray, centres: np.ndarray,
                  options: StartOptions) -> tuple[np.ndarray, np.ndarray]:
    """The cameras start ``kind`` begins at, cam_from_world ``(R [V, 3, 3], t [V, 3])``, from the
    pairs' ``relative`` poses and the model's rotations ``R0`` and ``centres``."""
    rotations = {ab: (T[:3, :3], w) for ab, (T, w) in relative.items()}
    R = R0 if kind == "model" else average_rotations(rotations, R0, options)
    c = average_centres(relative, R, centres) if kind == "pairs" else centres
    return R.copy(), -np.einsum("vij,vj->vi", R, c)


def ranked_starts(evidence: Evidence, start: np.ndarray, scale_view: int, opts: MapperOptions,
                  options: StartOptions,
                  adjust: rounds.AdjustOptions) -> Iterator[Reconstruction]:
    """Every start's adjustment finished, best first (lazily: a start's rounds past
    ``adjust.choose_after`` run only when the caller asks for it). The model's cameras
    ``start [V, 4, 4]`` (world_from_cam, in the frame of view 0); ``opts`` in the photos'
    pixels. Starts whose adjustment fails are left out."""
    ev = evidence
    cam_from_world = np.linalg.inv(start)
    R0, centres = cam_from_world[:, :3, :3], start[:, :3, 3]
    problem = (ev.centre, ev.tracks, scale_view, opts.max_error, opts.loss_scale, adjust)
    started = []            # per start: (its key after choose_after rounds, its adjustment then)
    for kind in options.kinds:
        R, t = start_cameras(kind, ev.relative, R0, centres, options)
        a = rounds.start_adjustment(R, t, ev.focal, ev.centre, ev.tracks)
        a = rounds.run_rounds(a, 0, adjust.choose_after, *problem)
        if a is not None:
            rec = rounds.as_reconstruction(a, ev.tracks, scale_view, adjust)
            started.append(((int(rec.registered.sum()),
                             -reprojection_score(rec, ev.tracks, ev.centre, opts)), a))
    ranked = sorted(range(len(started)), key=lambda i: started[i][0], reverse=True)
    for i in ranked:
        a = rounds.run_rounds(started[i][1], adjust.choose_after, None, *problem)
        if a is not None:
            yield rounds.as_reconstruction(a, ev.tracks, scale_view, adjust)

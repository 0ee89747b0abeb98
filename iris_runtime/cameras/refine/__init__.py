"""Step 9 of the camera solve: cameras a model predicted, refined by the photos.

The incremental mapper (``mapper``) spends most of the solve finding a start: starting pairs,
focal priors and view-by-view registrations, tried until one reconstruction explains the photos.
A model's camera head already gives every view a pose and the focal, so here they start a bundle
adjustment instead, and a ladder of checks decides whether its end is right (``ladder``):

- ``pairs``: the evidence, SIFT matches of every pair kept where the essential matrix at the
  model's focal explains them, and their tracks;
- ``starts``: the cameras the adjustment starts from (the model's and two built from the pairs'
  relative poses) and which ends best; ``rounds``: the adjustment's rounds;
- ``confirm``: another start agrees with the best -> kept;
- ``salvage``: else the views another start agrees on are kept, the others posed against them;
- ``witness``: else a quick incremental mapping of the same pairs confirms or salvages;
- else ``refine_cameras`` returns None and the caller runs the solve.

Like the solve it runs in ``canonical_order`` and its result is in the solve's terms
(``solve.CameraSolve``: its unit, root and point map), so it replaces a model's cameras as the
solve does (``replace.refine_model_cameras``). Each stage's settings are one options dataclass
(``RefineOptions`` groups them); the measurements behind the choices are in docs/CAMERAS.md
("Refining the model's cameras" and the sections after it).
"""
from .confirm import AgreementOptions, agreeing_pairs, agreeing_views, agreement
from .ladder import RefineOptions, refine_cameras
from .pairs import PairOptions
from .rounds import AdjustOptions
from .salvage import CappedPnP, SalvageOptions, salvage_core
from .starts import StartOptions, average_centres, average_rotations
from .witness import WitnessOptions

__all__ = ["refine_cameras", "RefineOptions", "PairOptions", "StartOptions", "AdjustOptions",
           "AgreementOptions", "SalvageOptions", "CappedPnP", "WitnessOptions",
           "average_rotations", "average_centres", "agreement", "agreeing_pairs",
           "agreeing_views", "salvage_core"]

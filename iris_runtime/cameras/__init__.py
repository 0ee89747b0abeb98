"""The cameras of a scene's photos, from the photos alone (numpy + OpenCV; no torch, no labels).

One entry point, ``solve_cameras(photos, depth_range) -> CameraSolve``, and its steps, one file
each, in the order they run (COLMAP's incremental structure from motion, scaled down):

1. ``features``: SIFT keypoints of each photo and their matches across every pair;
2. ``two_view``: per pair a fundamental matrix, a homography and the choice between them, and
   the relative pose;
3. ``tracks``: the keypoints that see one 3D point, across all photos;
4. ``triangulation``: points of tracks seen by posed views, and the checks they must pass;
5. ``bundle``: bundle adjustment of the poses, the points and the shared focal;
6. ``locate``: the pose of a photo from its matches to known points (PnP);
7. ``mapper``: the incremental mapper that runs 4-6 view by view;
8. ``solve``: the entry point (canonical order, scale, per-view status);
9. ``refine``: cameras a model predicted refined by the photos (matches, one bundle adjustment
   started from them: no mapper);
10. ``replace``: a model's predicted cameras replaced by the solve or refined, at the model's
   resolution (what ``IrisRuntime.encode(cameras="solve" | "refined")`` does).

Conventions (docs/ARCHITECTURE.md): OpenCV axes, ``world_from_cam`` camera-to-world with view 0 = I, pixel
(row i, col j) centred at (j + 0.5, i + 0.5). Measurements behind the choices: docs/CAMERAS.md.
"""
from .features import canonical_order
from .locate import PointMap, locate_photos, locate_views
from .mapper import MapperOptions
from .refine import refine_cameras
from .replace import ModelCameras, canonical_start, refine_model_cameras, replace_model_cameras
from .solve import DEPTH_TARGET, STATUSES, CameraSolve, solve_cameras, unit_range

__all__ = ["solve_cameras", "refine_cameras", "CameraSolve", "MapperOptions", "PointMap",
           "locate_photos", "locate_views", "replace_model_cameras", "refine_model_cameras",
           "ModelCameras", "canonical_order", "canonical_start", "DEPTH_TARGET", "STATUSES", "unit_range"]

"""Data classes shared by the generator's stages and its constants (see ``iris_train.synthetic``)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from iris_runtime.camera_io import GL_FROM_CV  # noqa: F401 (the renderer's axis flip)

#: Supersampling factor per axis (odd: see the module docstring). 3 -> 9 samples per pixel.
SUPERSAMPLE = 3
#: Marker colours (RGB, emissive on black metal: a fully covered pixel has this colour to within a
#: few levels; channels are 0 or 255 because pyrender applies a gamma curve to emissive values).
MARKER_COLORS = ((255, 0, 255), (0, 255, 255), (255, 255, 0), (0, 255, 0))
#: Marker sphere radius in scene units (~1.3-1.8 px at 64x64 and depth 0.6).
MARKER_RADIUS = 0.015
#: Icosphere subdivisions of markers: its faces lie at least 0.993 r from the centre.
MARKER_SUBDIVISIONS = 3
#: OpenGL clip planes (world units): far enough for every kind before its depth scaling.
ZNEAR, ZFAR = 0.02, 5.0


# ----------------------------------------------------------------------------------------------
# Output and backend-neutral scene description
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SceneData:
    """One multi-view scene. Views are ordered along the camera trajectory (the "Seq" order).

    images:         uint8   [V, H, W, 3] RGB
    world_from_cam: float64 [V, 4, 4]    camera-to-world, OpenCV axes
    K:              float64 [3, 3]       pixels, shared by all views; principal point at the centre
                                         for the classic kinds, off centre for the capture kinds
    depth:          float32 [V, H, W]    camera z-depth at pixel centres (along the optical axis,
                                         not euclidean distance); 0 where there is no geometry
    meta:           dict                 JSON-serialisable facts (seed, kind, fov, markers, ...);
                                         with ``markers=True`` also ``marker_coverage`` float32
                                         [V, M, H, W] (a numpy array: fraction of each pixel covered
                                         by marker m drawn alone, i.e. ignoring occlusion)
    """

    images: np.ndarray
    world_from_cam: np.ndarray
    K: np.ndarray
    depth: np.ndarray
    meta: dict = field(default_factory=dict)

    @property
    def n_views(self) -> int:
        return int(self.images.shape[0])

    @property
    def size(self) -> tuple[int, int]:
        """(height, width)."""
        return int(self.images.shape[1]), int(self.images.shape[2])


@dataclass
class MeshSpec:
    """A triangle mesh in world coordinates with per-vertex normals and texture coordinates."""

    positions: np.ndarray           # [N, 3] float32
    normals: np.ndarray             # [N, 3] float32, unit
    uvs: np.ndarray                 # [N, 2] float32 (textures repeat outside [0, 1])
    faces: np.ndarray               # [F, 3] uint32, counter-clockwise seen from the normal side
    texture: np.ndarray | None      # uint8 [h, w, 3] RGB base colour texture, or None
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)   # base colour factor (multiplies texture)
    roughness: float = 0.8
    emissive: tuple[float, float, float] | None = None    # markers: unlit constant colour
    marker_index: int = -1                                # >= 0 for marker spheres
    name: str = ""


@dataclass
class LightSpec:
    kind: str                                  # "directional" or "point"
    color: tuple[float, float, float]
    intensity: float                           # pyrender units (lux for directional, cd for point)
    position: np.ndarray | None = None         # [3] world, point lights
    direction: np.ndarray | None = None        # [3] world, direction the light travels


@dataclass
class SceneSpec:
    """Everything a renderer needs: geometry, materials, lights, background and cameras."""

    kind: str
    seed: int
    size: tuple[int, int]                      # (height, width)
    K: np.ndarray                              # [3, 3] float64 pixels at ``size``
    world_from_cam: np.ndarray                 # [V, 4, 4] float64 OpenCV
    meshes: list[MeshSpec]
    lights: list[LightSpec]
    ambient: tuple[float, float, float]
    background: tuple[float, float, float]     # RGB in [0, 1] where no geometry is seen
    markers_world: np.ndarray                  # [M, 3] float64 marker centres (M may be 0)
    meta: dict[str, Any]
    #: Capture kinds: the scene's median valid depth after rendering (the world and cameras are
    #: scaled to it, see ``render.render_spec``); None keeps the world's own units (classic kinds).
    depth_target: float | None = None
    #: Capture kinds: object centres [A, 3], scaled with the world; row 0 is the object every
    #: camera is aimed at (and sees), the others may leave the view along a walk.
    anchors_world: np.ndarray | None = None


# ----------------------------------------------------------------------------------------------

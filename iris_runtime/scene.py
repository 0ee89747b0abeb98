"""The runtime's value types: ``Scene`` (what the encoder leaves for rendering) and
``RenderResult`` (one rendered view), with the pose check a Scene applies to its cameras.

Cameras follow docs/ARCHITECTURE.md: OpenCV axes, ``world_from_cam`` 4x4, canonical frame = view 0's camera,
intrinsics in pixels with pixel centres at (j + 0.5, i + 0.5).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Sequence

import numpy as np

from . import geometry as G
from .errors import InputError
from .validation import check_world_from_cam

if TYPE_CHECKING:
    from .cameras import CameraSolve
    from .quality import RenderSettings

__all__ = ["Scene", "RenderResult", "check_pose", "CAMERA_SOURCES", "CAMERA_STATUSES"]

#: Values of ``Scene.camera_source``.
CAMERA_SOURCES = ("model", "solve", "refined", "mixed")
#: Values of ``Scene.camera_status`` (``iris_runtime.cameras.STATUSES``).
CAMERA_STATUSES = ("solved", "located", "unposed")


def _readonly(a, dtype) -> np.ndarray:
    out = np.array(a, dtype=dtype, copy=True, order="C")
    out.setflags(write=False)
    return out


def _readonly_numbers(value, dtype, name: str, expected: str) -> np.ndarray:
    """``_readonly(value, dtype)``, or ``InputError`` "NAME: expected EXPECTED, got TYPE" where
    ``value`` is not numbers."""
    try:
        return _readonly(value, dtype)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected {expected}, got {type(value).__name__}") from None


def check_pose(pose, name: str = "pose") -> np.ndarray:
    """``pose`` as a float64 4x4 rigid ``world_from_cam``, or ``InputError`` naming ``name`` and
    what is wrong (``validation.check_world_from_cam``, tolerance ``RIGID_ATOL``)."""
    return check_world_from_cam(pose, name)


@dataclass(frozen=True, eq=False)
class Scene:
    """What the encoder leaves for rendering (immutable; arrays are read-only copies).

    field_maps:     float32 [V, C', h, w]  per-view field maps the renderer samples
    world_from_cam: float64 [V, 4, 4]      predicted poses, OpenCV axes, view 0 = identity
    focal:          float64 [2]            shared focal (fx / W, fy / H), normalised
    K:              float64 [3, 3]         intrinsics in pixels of the model's resolution
    image_size:     (H, W)                 the model's resolution
    model_id:       sha256 of the encoder graph that made the scene ('' if unknown)
    reference_images: float32 [N, 3, H, W] in [0, 1], the model-resolution images the scene was
                    encoded from, what ``IrisRuntime.locate`` runs the encoder on (all N of them,
                    also after ``subset``, which keeps the frame and so the images that define it);
                    None for a Scene built by hand (``locate`` refuses it)
    image_index:    int64 [V], the row of ``reference_images`` that each view was encoded from
                    (``subset`` keeps it in step with the views): where explicit-colour models
                    read each view's photo. Default: ``arange(V)`` when there are V reference
                    images, else None (unknown; explicit-colour renders refuse such a Scene)
    camera_source:  where ``world_from_cam`` comes from: "model" (the encoder's prediction),
                    "solve" (``encode(..., cameras="solve")``: every view from the camera
                    solve of the photos, ``iris_runtime.cameras.solve_cameras``) or "mixed" (the
                    solve could not pose some views; they keep the model's camera, see
                    ``camera_status``). ``subset`` keeps the value of the scene it was cut from
    encoder_focal:  float64 [2], the focal the encoder predicted when ``focal`` is another one
                    (``cameras="solve"`` puts the solved focal in ``focal`` and ``K``); None
                    when ``focal`` is the encoder's. ``locate`` checks the reference images
                    against it
    camera_size:    (H, W) of the photos the cameras were solved at (their own resolution, at
                    most ``images.CAMERA_WORKING_SIZE`` on the longer side); None for the
                    model's cameras. ``K`` is the solved focal carried through the centre crop
                    and resize to the model's resolution
    camera_status:  per view, "solved" (in the joint solve), "located" (posed against the
                    solved views' points afterwards) or "unposed" (the solve could not pose it:
                    the model's camera); None for the model's cameras. ``subset`` keeps it in
                    step with the views
    camera_solve:   the ``iris_runtime.cameras.CameraSolve`` behind the cameras (its points and
                    descriptors, in this scene's frame and unit), what ``locate`` poses new
                    photos against; None for the model's cameras
    encoder_world_from_cam: float64 [V, 4, 4], the poses the encoder's camera head predicted
                    when ``world_from_cam`` holds other cameras (as ``encoder_focal``: None when
                    ``world_from_cam`` is the encoder's). Rigid, in the head's own frame and unit
                    (its view 0 = I before ``subset``), so compare it with other cameras only
                    after a similarity alignment. ``subset`` keeps it in step with the views
    photos:         per row of ``reference_images``, the photo as given (uint8 [h, w, 3]),
                    centre-cropped to the model's aspect and at most
                    ``colour.MAX_PHOTO_SIDE`` on its long side (``colour.keep_photo``): where
                    explicit-colour models read colours finer than the model's resolution
                    (``iris_runtime.colour``). None: the model-resolution images serve every
                    output size
    """
    field_maps: np.ndarray
    world_from_cam: np.ndarray
    focal: np.ndarray
    K: np.ndarray
    image_size: tuple[int, int]
    model_id: str = ""
    reference_images: np.ndarray | None = field(default=None, repr=False)
    image_index: np.ndarray | None = field(default=None, repr=False)
    camera_source: str = "model"
    encoder_focal: np.ndarray | None = field(default=None, repr=False)
    camera_size: tuple[int, int] | None = None
    camera_status: tuple[str, ...] | None = None
    camera_solve: "CameraSolve | None" = field(default=None, repr=False)
    # Last, not beside encoder_focal: callers build Scenes with positional arguments.
    encoder_world_from_cam: np.ndarray | None = field(default=None, repr=False)
    photos: tuple[np.ndarray, ...] | None = field(default=None, repr=False)
    # The photos' pyramid levels made by renders ({(id, size): (photo, level)}, colour._level).
    _levels: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self):
        # Every field checked once, here, in the order of its errors; then the read-only copies
        # replace the values given (a frozen dataclass: through object.__setattr__).
        maps, poses, focal, K, size = _check_cameras(self)
        V = maps.shape[0]
        refs, index = _check_references(self.reference_images, self.image_index, V, size)
        if not isinstance(self.camera_source, str) or self.camera_source not in CAMERA_SOURCES:
            raise InputError(f"camera_source: expected one of {list(CAMERA_SOURCES)}, got "
                             f"{self.camera_source!r}")
        enc_focal, enc_poses = _check_encoder_cameras(self.encoder_focal,
                                                      self.encoder_world_from_cam, V)
        cam_size, status = _check_solve(self.camera_size, self.camera_solve, self.camera_status, V)
        photos = self.photos
        if photos is not None:
            photos = _check_photos(photos, refs, size)
        for name, value in (("photos", photos), ("field_maps", maps), ("world_from_cam", poses),
                            ("focal", focal),
                            ("image_size", size), ("K", K), ("reference_images", refs),
                            ("image_index", index), ("encoder_focal", enc_focal),
                            ("camera_size", cam_size), ("camera_status", status),
                            ("encoder_world_from_cam", enc_poses)):
            object.__setattr__(self, name, value)

    @property
    def num_views(self) -> int:
        return self.field_maps.shape[0]

    def intrinsics(self, height: int | None = None, width: int | None = None) -> np.ndarray:
        """``K [3, 3]`` (float64) of the shared focal for an image of (height, width) pixels
        (default: the model's resolution), principal point at its centre. An image of another
        aspect than the model's widens the field of view: the model's image scaled to fit the
        shorter side (in the model's aspect) keeps its focal in pixels, the longer side sees
        more, so its centre crop of the model's aspect is that scaled image."""
        H, W = self.image_size
        h, w = height or H, width or W
        if h * W == w * H:                                   # the model's aspect: as always
            return G.intrinsics_from_focal(self.focal, h, w).astype(np.float64)
        scale = min(h / H, w / W)
        K = G.intrinsics_from_focal(self.focal, H * scale, W * scale).astype(np.float64)
        K[0, 2], K[1, 2] = w / 2.0, h / 2.0
        return K

    def subset(self, indices: Sequence[int]) -> "Scene":
        """A scene keeping only views ``indices`` (in that order) as references, in the same
        camera frame (poses are not re-based: view 0 of the original stays the world frame)."""
        try:
            idx = np.asarray(list(indices) if not isinstance(indices, np.ndarray) else indices)
        except (TypeError, ValueError):
            raise InputError(f"indices: expected a non-empty sequence of view indices (ints), "
                             f"got {indices!r}") from None
        V = self.num_views
        if idx.ndim != 1 or idx.size == 0 or not (np.issubdtype(idx.dtype, np.integer)):
            raise InputError(f"indices: expected a non-empty sequence of view indices (ints), "
                             f"got {indices!r}")
        if idx.min() < 0 or idx.max() >= V:
            raise InputError(f"indices: view index out of range 0..{V - 1}: {idx.tolist()}")
        if len(set(idx.tolist())) != idx.size:
            raise InputError(f"indices: repeated view index in {idx.tolist()} (a view counted "
                             f"twice would weigh twice in the view attention)")
        return Scene(self.field_maps[idx], self.world_from_cam[idx], self.focal, self.K,
                     self.image_size, self.model_id, self.reference_images,
                     None if self.image_index is None else self.image_index[idx],
                     self.camera_source, self.encoder_focal, self.camera_size,
                     None if self.camera_status is None
                     else tuple(self.camera_status[i] for i in idx.tolist()),
                     self.camera_solve,
                     None if self.encoder_world_from_cam is None
                     else self.encoder_world_from_cam[idx], self.photos)

    def __repr__(self) -> str:
        solved = "" if self.camera_size is None else f", camera_size={self.camera_size}"
        return (f"Scene(views={self.num_views}, field_maps={tuple(self.field_maps.shape)}, "
                f"image_size={self.image_size}, focal={np.round(self.focal, 4).tolist()}, "
                f"camera_source={self.camera_source!r}{solved})")


def _check_cameras(scene: Scene):
    """``Scene``'s field maps, cameras and image size checked -> read-only ``(field_maps
    float32 [V, C', h, w], world_from_cam float64 [V, 4, 4], focal float64 [2], K float64 [3, 3],
    image_size (H, W))``."""
    arrays = {}
    for name, dtype in (("field_maps", np.float32), ("world_from_cam", np.float64),
                        ("focal", np.float64), ("K", np.float64)):
        arrays[name] = _readonly_numbers(getattr(scene, name), dtype, name,
                                         "an array of numbers")
        if not np.all(np.isfinite(arrays[name])):
            raise InputError(f"{name}: contains NaN or inf")
    maps, poses, focal, K = (arrays[k] for k in ("field_maps", "world_from_cam", "focal", "K"))
    if maps.ndim != 4 or maps.shape[0] == 0:
        raise InputError(f"field_maps: expected [V, C', h, w] with V >= 1, got {maps.shape}")
    V = maps.shape[0]
    if poses.shape != (V, 4, 4):
        raise InputError(f"world_from_cam: expected [{V}, 4, 4], got {poses.shape}")
    if focal.shape != (2,) or K.shape != (3, 3):
        raise InputError(f"focal, K: expected [2] and [3, 3], got {focal.shape} and {K.shape}")
    if not np.all(focal > 0) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"focal, K: expected positive focal lengths, got focal "
                         f"{focal.tolist()} and K diagonal {np.diag(K).tolist()}")
    check_world_from_cam(poses, "world_from_cam", batch=True)
    size = tuple(int(s) for s in scene.image_size)
    if len(size) != 2 or min(size) <= 0:
        raise InputError(f"image_size: expected (H, W) positive, got {scene.image_size!r}")
    return maps, poses, focal, K, size


def _check_references(reference_images, image_index, V: int, size: tuple[int, int]):
    """``Scene.reference_images`` and ``image_index`` checked -> read-only ``(float32 [N, 3, H,
    W] or None, int64 [V] or None)``; the index defaults to ``arange(V)`` for V images."""
    refs = reference_images
    if refs is not None:
        refs = _readonly_numbers(refs, np.float32, "reference_images",
                                 "an array of numbers or None")
        if refs.ndim != 4 or refs.shape[0] == 0 or refs.shape[1:] != (3, *size):
            raise InputError(f"reference_images: expected [N, 3, {size[0]}, {size[1]}] with "
                             f"N >= 1, got {refs.shape}")
        if not (np.all(np.isfinite(refs)) and refs.min() >= 0.0 and refs.max() <= 1.0):
            raise InputError("reference_images: expected values in [0, 1] (no NaN or inf)")
    index = image_index
    if index is not None:
        if refs is None:
            raise InputError("image_index: given without reference_images (it indexes them)")
        try:
            index = np.asarray(index)
        except (TypeError, ValueError):
            index = np.asarray(None, dtype=object)
        if index.shape != (V,) or not np.issubdtype(index.dtype, np.integer) \
                or index.min() < 0 or index.max() >= refs.shape[0]:
            raise InputError(f"image_index: expected {V} integers in 0..{refs.shape[0] - 1} "
                             f"(the reference image of each view), got {image_index!r}")
        index = _readonly(index, np.int64)
    elif refs is not None and refs.shape[0] == V:
        index = _readonly(np.arange(V), np.int64)
    return refs, index


def _check_encoder_cameras(encoder_focal, encoder_world_from_cam, V: int):
    """``Scene.encoder_focal`` and ``encoder_world_from_cam`` checked -> read-only ``(float64 [2]
    or None, float64 [V, 4, 4] or None)``."""
    enc_focal = encoder_focal
    if enc_focal is not None:
        enc_focal = _readonly_numbers(enc_focal, np.float64, "encoder_focal",
                                      "[2] numbers or None")
        if enc_focal.shape != (2,) or not (np.all(np.isfinite(enc_focal))
                                           and np.all(enc_focal > 0)):
            raise InputError(f"encoder_focal: expected [2] positive finite numbers or None, "
                             f"got {enc_focal.tolist()}")
    enc_poses = encoder_world_from_cam
    if enc_poses is not None:
        enc_poses = check_world_from_cam(enc_poses, "encoder_world_from_cam", batch=True)
        if enc_poses.shape != (V, 4, 4):
            raise InputError(f"encoder_world_from_cam: expected [{V}, 4, 4] (one pose per "
                             f"view) or None, got {enc_poses.shape}")
        enc_poses = _readonly(enc_poses, np.float64)
    return enc_focal, enc_poses


def _check_solve(camera_size, camera_solve, camera_status, V: int):
    """``Scene.camera_size``, ``camera_solve`` and ``camera_status`` checked -> ``(camera_size
    (H, W) or None, camera_status tuple of V or None)``."""
    cam_size = camera_size
    if cam_size is not None:
        try:
            cam_size = tuple(int(x) for x in cam_size)
        except (TypeError, ValueError):
            cam_size = ()
        if len(cam_size) != 2 or min(cam_size) <= 0:
            raise InputError(f"camera_size: expected (H, W) positive or None, got "
                             f"{camera_size!r}")
    if camera_solve is not None:
        from .cameras import CameraSolve
        if not isinstance(camera_solve, CameraSolve):
            raise InputError(f"camera_solve: expected an iris_runtime.cameras.CameraSolve or "
                             f"None, got {type(camera_solve).__name__}")
    status = camera_status
    if status is not None:
        status = tuple(status) if not isinstance(status, str) else ()
        if len(status) != V or any(x not in CAMERA_STATUSES for x in status):
            raise InputError(f"camera_status: expected {V} values of {list(CAMERA_STATUSES)} "
                             f"or None, got {camera_status!r}")
    return cam_size, status


def _check_photos(photos, refs: np.ndarray | None, size: tuple[int, int]) -> tuple:
    """``Scene.photos`` checked: one uint8 [h, w, 3] array per reference image, of the model's
    aspect (its centre crop is itself) and within ``colour.MAX_PHOTO_SIDE``; read-only copies."""
    from .colour import MAX_PHOTO_SIDE
    from .images import plan_crop_resize
    if refs is None:
        raise InputError("photos: given without reference_images (one photo per reference image)")
    if isinstance(photos, np.ndarray) or not isinstance(photos, (list, tuple)) \
            or len(photos) != refs.shape[0]:
        raise InputError(f"photos: expected a list of {refs.shape[0]} uint8 [h, w, 3] arrays (one "
                         f"per reference image), got {type(photos).__name__}"
                         + (f" of {len(photos)}" if isinstance(photos, (list, tuple)) else ""))
    out = []
    for i, p in enumerate(photos):
        if not isinstance(p, np.ndarray) or p.dtype != np.uint8 or p.ndim != 3 \
                or p.shape[2] != 3 or min(p.shape[:2]) == 0:
            got = (f"{p.dtype} array of shape {p.shape}" if isinstance(p, np.ndarray)
                   else type(p).__name__)
            raise InputError(f"photos[{i}]: expected a uint8 [h, w, 3] array, got {got}")
        h, w = p.shape[:2]
        crop = plan_crop_resize(h, w, *size)
        if (crop.crop_h, crop.crop_w) != (h, w) or max(h, w) > MAX_PHOTO_SIDE:
            raise InputError(f"photos[{i}]: expected the model's aspect {size[0]}:{size[1]} and at "
                             f"most {MAX_PHOTO_SIDE} pixels a side (colour.keep_photo), got "
                             f"{h}x{w}")
        # colour.keep_photo's arrays (read-only, owning their memory) are kept as they are.
        owned = p.base is None and not p.flags.writeable and p.flags.c_contiguous
        out.append(p if owned else _readonly(p, np.uint8))
    return tuple(out)


@dataclass(frozen=True, eq=False)
class RenderResult:
    """One rendered view.

    image:       uint8   [H, W, 3] RGB
    image_float: float32 [H, W, 3] RGB in [0, 1] (what the renderer returned)
    depth:       float32 [H, W]    soft camera depth sum_m w_m z_m in model units, within
                                   [near, far]; 0 where no sample sees any reference view
    timings:     seconds per stage (``load``/``encode`` when images were given, ``rays``: numpy
                 geometry, ``renderer``: ONNX Runtime, ``upsample`` when scale < 1, ``coarse``
                 with ``refine`` / ``depth_window``: wall seconds of the coarse pass and of
                 choosing what to march again (``rays`` and ``renderer`` sum both passes),
                 ``total``)
    work:        what the renderer graph was given: ``calls``, and over the calls the sums of
                 R (``rays``), R*S (``points``), R*S*V' (``point_views``) and R*S^2
                 (``ray_pairs``), R/S/V' the rays, samples and views of a call (FLOP counts);
                 with ``refine`` / ``depth_window`` also ``coarse_rays``, ``refined_rays``,
                 ``windowed_rays``, ``kept_samples`` and ``pixels`` (``adaptive.Rendered``:
                 the fraction refined is refined_rays / pixels)
    settings:    the ``RenderSettings`` used
    """
    image: np.ndarray
    image_float: np.ndarray
    depth: np.ndarray
    timings: dict = field(default_factory=dict)
    work: dict = field(default_factory=dict)
    settings: "RenderSettings | None" = None

    @property
    def coverage(self) -> float:
        """The fraction of pixels whose ray meets some reference view's field of view (``depth``
        > 0; where the march ran at a reduced size, of its linearly upsampled depth, so a pixel
        beside a covered one counts). 0: the camera sees none of the scene, and every pixel is
        the renderer's colour of an empty ray, not a view of anything."""
        return float(np.count_nonzero(self.depth > 0)) / max(self.depth.size, 1)


@dataclass(frozen=True, eq=False)
class RenderJob:
    """One ``IrisRuntime.render`` call, checked (internal): what its ray march needs (arrays as
    the checks returned them).

    scene:          the Scene rendered from (encoded by the call when it was given images)
    world_from_cam: float64 [4, 4]   target pose
    K:              [3, 3]           target intrinsics in pixels of ``march_size``
    size:           (H, W)           the output's pixels
    march_size:     (h, w)           the pixels marched (``RenderSettings.march_size``)
    settings:       RenderSettings   the knobs, resolved
    samples:        int              samples per ray
    chunk_rays:     int              rays per renderer call
    graph:          str              the renderer graph of the call's precision
    select_views:   bool             per-point top-k on ``renderer_views``
    photos:         float32 [V, 3, H, W] or None   each view's photo (explicit colour)
    kept_photos:    per view uint8 [h, w, 3] or None   each view's photo as given
                                                    (``Scene.photos``; None: none kept)
    """
    scene: Scene
    world_from_cam: np.ndarray
    K: np.ndarray
    size: tuple[int, int]
    march_size: tuple[int, int]
    settings: RenderSettings
    samples: int
    chunk_rays: int
    graph: str
    select_views: bool
    photos: np.ndarray | None
    kept_photos: tuple | None = None

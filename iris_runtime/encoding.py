"""The encoder graph's half of ``IrisRuntime``: photos -> a ``Scene`` (``encode``) and photos ->
their poses in a scene (``locate``).

``Encoding`` is a mixin of ``iris_runtime.runtime.IrisRuntime``, not a class of its own: it reads
the runtime's ``manifest``, ``image_size``, ``near``, ``far`` and ``max_views``, runs graphs through
its ``_session(name)``, bounds numpy's BLAS with its ``_blas_threads()`` and checks a Scene with its
``_check_scene``. Those stay in the runtime (its sessions and shared checks), so a test or a
benchmark that replaces one of them on an instance is obeyed here too.

References and queries: ``encode`` runs the encoder graph with every image a reference.
``locate`` runs it again on the scene's reference images (kept, read-only, in the ``Scene``)
followed by the photos as queries (``is_reference = [True] * V + [False] * Q``): a reference's
tokens attend to references only, a query's to the references and itself, so the references'
features and cameras are those of the scene (bitwise, in ONNX Runtime) and the query's pose comes
out in the scene's frame. The scene is not changed and queries never see each other.
"""
from __future__ import annotations

import os
import time

import numpy as np

from . import geometry as G
from .colour import keep_photo
from .errors import InputError, ModelFileError
from .images import fit_to_model, load_image
from .io_spec import FIELD_MAPS, FOCAL, IMAGES, IS_REFERENCE, WORLD_FROM_CAM
from .limits import MAX_ENCODER_TOKENS, MAX_LOCATE_CALLS
from .manifest import CAMERAS, camera_name
from .scene import Scene

__all__ = ["Encoding"]


def _is_single_image(x) -> bool:
    """One image (a path, a PIL image, an HxW(xC) array) rather than a sequence of images."""
    return (isinstance(x, (str, os.PathLike, bytes)) or hasattr(x, "getpixel")
            or (isinstance(x, np.ndarray) and x.ndim != 4))



class Encoding:
    """``IrisRuntime``'s ``encode`` and ``locate`` and the encoder graph runs behind them (module
    docstring: what it needs of the runtime)."""

    # -- photos -> the encoder's batch -------------------------------------------------------
    def _load_photos(self, images, name: str = "images", limit: int | None = None,
                     single: bool = False) -> list[np.ndarray]:
        """Images -> uint8 RGB photos [H_i, W_i, 3] at their own resolution (``name``: the
        argument in messages; ``limit``: most images accepted, default ``max_views``; ``single``:
        ``images`` is a one-element list made from one image called ``name``)."""
        if _is_single_image(images):
            raise InputError(f"{name}: expected a sequence of images (paths, PIL images or "
                             f"HxWx3 uint8 arrays), got a single {type(images).__name__}; "
                             f"wrap it in a list")
        try:
            items = list(images)
        except TypeError:
            raise InputError(f"{name}: expected a sequence of images or a Scene, got "
                             f"{type(images).__name__}") from None
        if not items:
            raise InputError(f"{name}: expected at least one image, got an empty sequence")
        if limit is None and len(items) > self.max_views:
            raise InputError(f"{name}: {len(items)} images, at most {self.max_views} per encode "
                             f"for this model (MAX_ENCODER_TOKENS = {MAX_ENCODER_TOKENS}: the "
                             f"encoder's memory grows with the square of the views)")
        if limit is not None and len(items) > limit:
            raise InputError(f"{name}: {len(items)} images, at most {limit} per locate for this "
                             f"scene and model (MAX_LOCATE_CALLS = {MAX_LOCATE_CALLS} encoder calls "
                             f"of up to {self.max_views} views, the scene's references included)")
        return [load_image(item, name if single else f"{name}[{i}]") for i, item in enumerate(items)]

    def _model_batch(self, photos: list[np.ndarray]) -> np.ndarray:
        """uint8 photos -> float32 [V, 3, H, W] in [0, 1] at the model's resolution
        (``fit_to_model``: centre crop to the model's aspect, resize)."""
        H, W = self.image_size
        batch = np.empty((len(photos), 3, H, W), dtype=np.float32)
        for i, photo in enumerate(photos):
            batch[i] = fit_to_model(photo, H, W)[0].transpose(2, 0, 1)
        batch *= np.float32(1.0 / 255.0)
        return batch

    def _load_images(self, images, name: str = "images", limit: int | None = None,
                     single: bool = False) -> np.ndarray:
        """Images -> float32 [V, 3, H, W] in [0, 1] at the model's resolution (arguments as
        ``_load_photos``)."""
        return self._model_batch(self._load_photos(images, name, limit, single))


    # -- the encoder graphs ------------------------------------------------------------------
    def _run_encoder(self, batch: np.ndarray, is_reference: np.ndarray):
        """The encoder graph on ``batch [V, 3, H, W]`` with ``is_reference`` bool [V] -> field_maps
        float32 [V, C', h, w], world_from_cam float32 [V, 4, 4], focal float32 [2], checked."""
        return self._run_checked("encoder", (FIELD_MAPS, WORLD_FROM_CAM, FOCAL), batch,
                                 is_reference)

    def _run_cameras(self, batch: np.ndarray, is_reference: np.ndarray):
        """``_run_encoder``'s cameras alone: world_from_cam float32 [V, 4, 4], focal float32 [2],
        checked. From the model's "encoder_cameras" graph where it has one (the camera head on its
        own encoder: the field's encoder is not run), else from the encoder graph."""
        if "encoder_cameras" not in self.manifest.graphs:
            return self._run_encoder(batch, is_reference)[1:]
        return self._run_checked("encoder_cameras", (WORLD_FROM_CAM, FOCAL), batch, is_reference)

    def _run_checked(self, graph: str, names: tuple[str, ...], batch: np.ndarray,
                     is_reference: np.ndarray) -> tuple[np.ndarray, ...]:
        """Outputs ``names`` of an encoder ``graph`` on ``batch`` and ``is_reference``; a wrong
        shape or a NaN or inf (finite images in [0, 1] never give one) is a ``ModelFileError``
        naming the graph's file."""
        outs = self._session(graph).run(
            list(names), {IMAGES: batch, IS_REFERENCE: np.ascontiguousarray(is_reference, bool)})
        V, channels = batch.shape[0], self.manifest.field_channels

        def fits(name: str, x: np.ndarray) -> bool:
            if name == FIELD_MAPS:
                return x.ndim == 4 and x.shape[0] == V and (not channels or x.shape[1] == channels)
            return x.shape == {WORLD_FROM_CAM: (V, 4, 4), FOCAL: (2,)}[name]

        path = self.manifest.graphs[graph].path
        expected = {FIELD_MAPS: "[V, C', h, w]", WORLD_FROM_CAM: "[V, 4, 4]", FOCAL: "[2]"}
        if not all(fits(n, x) for n, x in zip(names, outs)):
            raise ModelFileError(
                f"{path}: {graph} returned " + ", ".join(f"{n} {x.shape}" for n, x in
                                                         zip(names, outs))
                + f" for {V} views; expected " + ", ".join(expected[n] for n in names))
        if not all(np.all(np.isfinite(x)) for x in outs):
            raise ModelFileError(f"{path}: {graph} returned NaN or inf for finite images in "
                                 f"[0, 1] (broken weights?)")
        return tuple(outs)

    # -- encode ------------------------------------------------------------------------------
    def encode(self, images, cameras: str | None = None) -> Scene:
        """Run the encoder on ``images`` (a sequence of HxWx3 uint8 RGB arrays, PIL images or
        file paths, any size: centre-cropped to the model's aspect ratio and resized, see
        ``iris_runtime.images.fit_to_model``), every image a reference -> an immutable ``Scene``
        (which keeps the model-resolution images for ``locate``).

        cameras: None (default): ``default_cameras``, the cameras this model's renderer was
                 trained with (the manifest's "cameras").
                 "model": the encoder's predicted cameras and focal.
                 "solve": the field maps are the encoder's as always, but the cameras are
                 solved from the photos themselves at their own resolution (a copy at most
                 ``images.CAMERA_WORKING_SIZE`` on the longer side, ``images.camera_copies``)
                 by ``iris_runtime.cameras.solve_cameras``: SIFT matches across every pair,
                 two-view model selection, incremental mapping with bundle adjustment of the
                 poses and the focal; the centres scaled so that the scene's median point
                 depth lies ``cameras.DEPTH_TARGET`` of the way into the renderer's depth range
                 [near, far]. The solved focal, carried through the crop and resize to the
                 model's resolution, becomes the Scene's ``focal`` and ``K`` (the encoder's
                 focal and poses are kept in ``Scene.encoder_focal`` and
                 ``Scene.encoder_world_from_cam``); ``Scene.camera_size`` says the resolution
                 the cameras were solved at and ``Scene.camera_status`` how each view was
                 posed. A view the solve cannot pose keeps the encoder's camera
                 (``camera_status`` "unposed", ``camera_source`` "mixed"; all of them, and
                 ``camera_source`` "model", when view 0 is not posed, since it defines the
                 frame). Cost and accuracy: docs/CAMERAS.md.
                 "refined": as "solve", but the encoder's cameras and focal are the start of
                 one bundle adjustment on the same matches (``cameras.refine_cameras``: no
                 incremental mapper, a fraction of the solve's time) instead of being replaced;
                 ``camera_source`` "refined". The start is the encoder's prediction with the
                 photos in ``cameras.canonical_order`` (a second encoder run where that order
                 differs), so that, as the solve's, the cameras do not depend on the order the
                 photos come in. Where the photos cannot constrain the cameras
                 (fewer than two views keep enough observations), view 0 is not refined, or the
                 adjustment from no other start agrees with the one kept (a wrong minimum,
                 ``cameras.refine.AgreementOptions``), the solve replaces them as with "solve";
                 where it cannot pose view 0 either, the start is kept (``camera_source``
                 "model"), and the encoder's own cameras beside it when they differ.
                 As accurate as the encoder's start is close (docs/CAMERAS.md, "Refining the
                 model's cameras").
        """
        return self._encode(images, {}, self._check_cameras(
            self.default_cameras if cameras is None else cameras))

    @staticmethod
    def _check_cameras(cameras) -> str:
        cameras = camera_name(cameras)          # a former name (manifest.CAMERA_ALIASES) too
        if not isinstance(cameras, str) or cameras not in CAMERAS:
            raise InputError(f"cameras: expected one of {list(CAMERAS)}, got {cameras!r}")
        return cameras

    def _encode(self, images, timings: dict, cameras: str = "model") -> Scene:
        t0 = time.perf_counter()
        photos = self._load_photos(images)
        batch = self._model_batch(photos)
        t1 = time.perf_counter()
        maps, world_from_cam, focal = self._run_encoder(batch, np.ones(batch.shape[0], bool))
        t2 = time.perf_counter()
        timings["load"] = timings.get("load", 0.0) + (t1 - t0)
        timings["encode"] = timings.get("encode", 0.0) + (t2 - t1)
        H, W = self.image_size
        focal64 = focal.astype(np.float64)
        poses64 = world_from_cam.astype(np.float64)
        model_id = self.manifest.graphs["encoder"].sha256
        model_K = G.intrinsics_from_focal(focal64, H, W)
        # Explicit colour: the photos as given (cropped, bounded) for colours finer than the
        # model's pixels (iris_runtime.colour).
        kept = (tuple(keep_photo(p, (H, W)) for p in photos) if self.manifest.explicit_rgb
                else None)
        if cameras == "model":
            return Scene(maps, poses64, focal64, model_K, (H, W), model_id, batch, photos=kept)
        from .cameras import canonical_start, refine_model_cameras, replace_model_cameras
        with self._blas_threads():
            if cameras == "refined":
                start, start_focal = canonical_start(
                    photos, poses64, focal64,
                    lambda perm: self._run_cameras(batch[perm], np.ones(len(perm), bool)))
                cams = refine_model_cameras(photos, start, start_focal, (H, W),
                                            self.unit_range)
            else:
                cams = replace_model_cameras(photos, poses64, focal64, (H, W),
                                             self.unit_range)
        timings["cameras"] = timings.get("cameras", 0.0) + (time.perf_counter() - t2)
        # The encoder's own cameras (what locate checks the references against) are kept
        # wherever the scene's are others: the solve's, the refinement's, and also the model's
        # when they are the refinement's start in canonical_order (another run of the head:
        # another focal and frame) that its fallback kept because the solve could not pose
        # view 0 either.
        own = (cams.source == "model" and np.array_equal(cams.world_from_cam, poses64)
               and np.array_equal(cams.focal, focal64))
        return Scene(maps, cams.world_from_cam, cams.focal, cams.K, (H, W), model_id, batch,
                     camera_source=cams.source,
                     encoder_focal=None if own else focal64,
                     camera_size=cams.camera_size, camera_status=cams.status,
                     camera_solve=cams.solve,
                     encoder_world_from_cam=None if own else poses64,
                     photos=kept)

    # -- locate ------------------------------------------------------------------------------
    def locate(self, scene: Scene, image, *, with_status: bool = False):
        """Pose of a new photo in ``scene``'s frame, without changing the scene.

        scene:  a ``Scene`` from ``encode`` of this model (or its ``subset``: same frame).
        image:  one photo (path, PIL image or HxWx3 array, any size: fitted like ``encode``'s
                images) or a sequence of them.

        Runs the encoder graph on the scene's reference images followed by the photo(s) as
        queries: each photo sees the references and itself, never the other photos, so locating
        several at once equals locating them one by one, up to float rounding (batches of at most
        ``max_views`` views per encoder call, references included, and at least one photo per
        call; at most ``MAX_LOCATE_CALLS`` calls). Returns ``world_from_cam`` float64 ``[4, 4]``
        for one photo, ``[Q, 4, 4]`` for a sequence (OpenCV axes, the scene's canonical frame:
        its first reference is the identity; the scene's shared focal applies).

        For a Scene whose cameras were solved from its photos (``Scene.camera_solve``, from
        ``cameras="solve"``) the pose is solved the same way, with the scene's cameras held
        fixed: the photo, at its own resolution brought to ``Scene.camera_size`` (a centre crop
        when its aspect differs: it is taken to come from the same camera), is matched against
        the scene's points and posed by PnP (``iris_runtime.cameras.locate_photos``), in the
        scene's frame and unit. A photo it cannot pose gets the model's prediction, which lies
        in the frame of the encoder's reference cameras (same view 0 but another unit).
        Otherwise the pose is the model's prediction.

        with_status: also return, per photo, "located" (posed against the scene's points) or
        "unposed" (the model's prediction): ``(poses, status)``, status a str or a tuple.
        """
        if not isinstance(scene, Scene):
            raise InputError(f"scene: expected a Scene from IrisRuntime.encode, got "
                             f"{type(scene).__name__}")
        self._check_scene(scene, "scene")
        refs = scene.reference_images
        if refs is None:
            raise InputError("scene: this Scene holds no reference images (it was built by hand, "
                             "not by IrisRuntime.encode); locate needs them to run the encoder")
        single = _is_single_image(image)
        if not single and (isinstance(image, (dict, set)) or not hasattr(image, "__iter__")):
            raise InputError(f"image: expected one photo (a path, a PIL image or an HxWx3 array) "
                             f"or a sequence of them, got {type(image).__name__}")
        per_call = max(1, self.max_views - refs.shape[0])
        photos = self._load_photos([image] if single else image, "image",
                                   limit=per_call * MAX_LOCATE_CALLS, single=single)
        poses = self._query_poses(scene, self._model_batch(photos), per_call)
        located = np.zeros(len(photos), bool)
        solve = scene.camera_solve
        if solve is not None:
            with self._blas_threads():
                solved, located = solve.locate(photos)
            poses = np.where(located[:, None, None], solved, poses)
        if not with_status:
            return poses[0] if single else poses
        status = tuple("located" if ok else "unposed" for ok in located.tolist())
        return (poses[0], status[0]) if single else (poses, status)

    def _query_poses(self, scene: Scene, queries: np.ndarray, per_call: int) -> np.ndarray:
        """The model's poses of ``queries [Q, 3, H, W]`` in ``scene`` -> float64 ``[Q, 4, 4]``:
        the camera graph on the scene's references followed by at most ``per_call`` queries at a
        time, or ``InputError`` when the references do not give back the scene's encoder focal
        (they are not the images it was encoded from)."""
        refs = scene.reference_images
        N = refs.shape[0]
        poses = []
        for start in range(0, queries.shape[0], per_call):
            chunk = queries[start:start + per_call]
            batch = np.concatenate([refs, chunk])
            world_from_cam, focal = self._run_cameras(batch, np.arange(batch.shape[0]) < N)
            expected = scene.focal if scene.encoder_focal is None else scene.encoder_focal
            if np.abs(focal.astype(np.float64) - expected).max() > 1e-6:   # bitwise when real
                raise InputError(f"scene: its reference_images give focal {focal.tolist()}, not "
                                 f"the encoder's {expected.tolist()} of the scene (not the "
                                 f"images it was encoded from)")
            poses.append(world_from_cam[N:].astype(np.float64))
        return np.concatenate(poses)

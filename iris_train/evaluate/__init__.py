"""iris-eval: novel view synthesis (PSNR, SSIM) and relative pose accuracy (RPA) of an IRIS model.

    iris-eval runs/tiny/last.pt synthetic:heldout --json eval.json
    iris-eval out/ my_scenes/ --scenes 10 --grid grid.png      # an exported model, users' data
    iris-eval out/ real/castle --cameras true                  # the data's own cameras
    iris-eval out/ synthetic:heldout --size 256 --json eval256.json   # at 256x256 output

MODEL is a training checkpoint (``.pt``, run in torch) or an exported model directory (holding
``iris.json``, run with ``iris_runtime.IrisRuntime``: the numbers of what is served). DATA is
``synthetic:heldout`` (the held-out synthetic scenes ``iris_train.data.HELDOUT_SEEDS``, rendered
once and cached), ``synthetic:capture-heldout`` (the capture-like held-out scenes,
``CAPTURE_HELDOUT_SEEDS``: photos at 256x256 with camera effects; ``synthetic:capture-validation``
the same kinds on ``CAPTURE_VALIDATION_SEEDS``, where capture-like choices are made) or a folder of scene folders (``iris_train.data.load_dataset_folder``; cameras
optional; ``scripts/real_sets.py`` builds the real ones, docs/REAL.md). The metrics themselves
(``iris_train.metrics``) are numpy + OpenCV only.

The package, one file per stage: ``protocol`` (split, orders, photo baselines), ``scenes``
(MODEL/DATA arguments, a scene at the model's resolution), ``backends`` (torch checkpoint or
exported runtime behind one interface), ``cameras`` (where the references' and targets' cameras
come from), ``evaluation`` (``evaluate``), ``report`` (tables, JSON, grid), ``cli``.

Protocol (docs/ARCHITECTURE.md, "Conventions", the paper's appendix scaled down):

- A scene has N = 8 frames (``--views``) in trajectory order. Scenes with more frames are
  subsampled evenly along the stored order; scenes with fewer are skipped.
- Fixed split: targets are frames ``TARGET_FRAMES = (1, 4, 6)``, references the others
  (0, 2, 3, 5, 7); for N != 8 see ``split_frames``.
- References are encoded isolated: the scene (features, cameras, focal) is ``encode`` of the
  reference frames alone, so no target image reaches it. The targets are *queries*: their poses
  are predicted from the target images in the references' frame by ``locate``
  (``IrisRuntime.locate`` for an exported model, ``IrisModel.locate`` for a checkpoint: one encoder
  run over references + targets in which a target sees the references and itself only). The
  targets are rendered from the references at their located poses, at the model's resolution,
  and compared with the target images: PSNR and SSIM (``iris_train.metrics``), per image,
  averaged over targets, then over scenes.
- Pose: RPA@5/15/30 of the N predicted poses (references from ``encode``, targets from
  ``locate``) against the ground truth over all frame pairs; and **locate RPA**
  (``locate_rpa@5/15/30``) over the pairs that involve at least one target (target-reference and
  target-target pairs: 18 of the 28 at N = 8), i.e. every pair whose relative pose depends on a
  located camera. The identity-pose baseline reports both too.
- Soft depth: ``depth_spearman`` (``iris_train.metrics.depth_spearman``), the Spearman rank
  correlation of each target's rendered soft depth with its true depth over the pixels that see
  geometry (true depth > 0), averaged over targets, then over scenes. Only scenes with a true
  depth count (the synthetic ones; users' folders have none: ``null`` when no scene has one); a
  target with fewer than 3 such pixels or a constant depth map is left out of its scene's mean.
- Two input orders: **Seq** (frames as stored) and **Rand** (a fixed per-scene permutation from
  ``RAND_SEED`` and the scene's index, ``presentation_order``). Targets and references are the same
  frames in both; in Rand the references are presented to ``encode`` in the order they take in the
  permutation, so the first reference of the permutation becomes the canonical frame (view 0 must
  be a reference; RPA does not depend on the world frame), and the targets are located in their
  permutation order (queries do not see each other, so that order does not matter).
- Baselines on the same scenes and frames: *best reference* (per target, the reference image with
  the highest PSNR against it, chosen knowing the target: ``best_reference``; defined for every
  scene, the bar where no true cameras exist), *nearest reference* (the reference image whose
  ground-truth camera is closest to the target's: rotation angle in radians + centre distance
  divided by the mean distance of the scene's camera centres from their centroid; see
  ``nearest_reference``) and *mean colour* (every pixel the mean RGB of the reference images)
  for NVS; *identity poses* (all cameras predicted at the canonical one) for RPA. With the
  zero-translation convention of ``iris_train.metrics`` identity poses score 0 on every pair
  whose cameras are not at the same place.
- Scenes without ground-truth cameras (users' folders) count towards the model's PSNR/SSIM and the
  best-reference and mean-colour baselines only; pose metrics and the nearest-reference baseline
  average over the scenes with cameras (``null`` in the JSON when there are none).
- ``--cameras solve``: the references' cameras (and the focal) are the camera solve of the
  references' **photos at their own resolution** (``PreparedScene.photos``: a folder's files as
  stored, the synthetic sets rendered at ``SYNTHETIC_PHOTO_SIZE``), scaled to the model's units
  (``iris_runtime.cameras.replace_model_cameras``, as ``IrisRuntime.encode(photos,
  cameras="solve")`` does; the model itself sees the frames at its resolution), and the
  targets are posed against the solve's points with its cameras fixed
  (``CameraSolve.locate``, as ``IrisRuntime.locate``; a target it cannot pose
  keeps the model's located pose); ``--locate model`` keeps the model's ``locate`` instead.
- ``--cameras true``: the data's own cameras (a folder's ``transforms.json`` or COLMAP text, the
  synthetic scenes' true cameras; evaluation only, training never sees them), re-based on view 0
  of the presentation and scaled by the solve's depth rule (``cameras.true_cameras``: the median
  depth of the reference images' triangulated points put ``cameras.DEPTH_TARGET`` of the
  way into [near, far]), with the true focal carried through the crop and resize to the model's
  resolution; the targets at their true cameras (``--locate`` can pick another source). The
  renderer's error is then told apart from the cameras'. The encoder still sees the references
  alone; only the cameras it predicted are replaced.
- Every scene's record (JSON ``scenes``, the printed per-scene table) says where its cameras came
  from: the Scene's camera source ("model", "solve", "mixed", "true"), which references the
  solve posed and which targets it located, and the number of **fallbacks**: views
  that were to get a solved camera and kept the camera head's instead. With anything but model
  cameras each order's summary counts the scenes per source and the fallbacks.
- The camera head beside the cameras that replaced it: ``reference_rpa@5/15/30`` is the RPA of
  the rendered cameras over the pairs of two references (the 10 of 28 pairs that
  ``locate_rpa`` leaves out), and with ``--cameras solve`` or ``true``
  ``head_reference_rpa@5/15/30`` the same for the camera head's own cameras of the references
  (kept in ``Scene.encoder_world_from_cam``; ``null`` with model cameras). References only: a
  scene's head cameras are its references' (the targets' poses come from ``--locate``). ``--grid``
  draws the head's cameras (green, references) beside the rendered (red) and true (blue) ones,
  each set similarity-aligned to the true cameras on its own.
- LPIPS is left out: it needs pretrained network weights that cannot be fetched here.

Output size (``--size S``, ``evaluate(..., size=S)``; a square model): the same protocol scored at
S x S instead of the model's resolution.

- Ground truth at S: each frame's photo at its own resolution (``PreparedScene.photos``: a
  folder's files as stored, the synthetic sets' 256x256 renders, ``SYNTHETIC_PHOTO_SIZE``, from
  the same seeds and cache as the photos above) centre-cropped to a square and shrunk to S with
  ``cv2.INTER_AREA`` (``scenes.to_output_size``). A photo smaller than S on its shorter side is
  refused (``InputError`` naming the photos' size and S): ground truth is never enlarged. The
  true depth is brought to S by the same crop and a nearest-neighbour resize.
- The references are handed to ``encode`` as photos at their own resolution (the encoder fits
  them to the model itself; the model's images of the scene are then those fits, which a
  synthetic scene's 64x64 renders only approximate), the targets are located from their
  photos fitted to the model, and the cameras (``--cameras``, ``--locate``), split and Rand/Seq
  orders are as above. A pose does not depend on the output size: it is rendered at S with
  intrinsics of the same normalised focal (``IrisRuntime.render(scene, pose, height=S,
  width=S)``; a checkpoint renders at S in torch, its explicit colours sampled from the
  reference photos brought to S).
- PSNR/SSIM of the model and the photo baselines (best and nearest reference, mean colour: the
  same definitions) at S, ``depth_spearman`` at S, and the baseline **upsampled**: the render of
  the same pose at the model's resolution (clipped to [0, 1]) resized to S with
  ``cv2.INTER_CUBIC`` (clipped again), i.e. what the model gives without rendering at S. Each
  order's JSON then holds ``"output_size": [S, S]``, ``"model_size": [H, W]`` and
  ``baselines.upsampled`` {psnr, ssim} (per scene too); the tables an "upsampled" row and
  column. ``--grid`` draws the S x S photos, renders and depths.
- ``--quality PRESET`` (``iris_runtime.quality.QUALITY_PRESETS``) is passed to every
  ``IrisRuntime.render`` (the model-resolution render of "upsampled" too), with or without
  ``--size``; a checkpoint renders "exact" only.
- Without ``--size`` and ``--quality`` nothing changes: same calls, same numbers, same JSON.

PSNR per image is capped at ``PSNR_CAP`` dB (an identical image would otherwise give inf).
"""
from __future__ import annotations

from .backends import RuntimeBackend, TorchBackend, backend_for, focal_of
from .cameras import CAMERA_MODES, LOCATE_MODES, TrueCameras, true_cameras
from .cli import main
from .evaluation import evaluate
from .protocol import (DEFAULT_VIEWS, ORDERS, PSNR_CAP, RAND_SEED, TARGET_FRAMES, best_reference,
                       locate_rpa, nearest_reference, presentation_order, rand_permutation,
                       split_frames)
from .report import format_scenes, format_table, save_grid, write_json
from .scenes import SYNTHETIC_SETS, load_evaluable, load_scenes, prepare_scene, true_depth_and_K

__all__ = ["evaluate", "split_frames", "rand_permutation", "presentation_order", "nearest_reference",
           "best_reference", "format_table", "format_scenes", "load_scenes", "load_evaluable",
           "TARGET_FRAMES", "DEFAULT_VIEWS", "RAND_SEED", "ORDERS", "PSNR_CAP", "SYNTHETIC_SETS",
           "CAMERA_MODES", "LOCATE_MODES", "TrueCameras", "true_cameras", "write_json",
           "save_grid", "main"]

# The names the module had before it became a package (tests and scripts import them).
_locate_rpa = locate_rpa
_true_depth_and_K = true_depth_and_K
_backend = backend_for
_TorchBackend = TorchBackend
_RuntimeBackend = RuntimeBackend
_focal_of = focal_of
_prepare_scene = prepare_scene

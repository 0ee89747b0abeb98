"""The camera picture of a wide-baseline walk: ViSP ``Castle-simu`` frames 1, 6, ..., 36 (the
8 widest-spaced frames of ``benchmarks/camera_solve.py``), solved by ``iris_runtime.cameras`` the
way ``IrisRuntime.encode`` solves them (on copies at most 512 pixels long), drawn by
``iris_runtime.camera_plot.draw_cameras`` over the true cameras (similarity-aligned), at 320x240
and at 640x480.

    python scripts/camera_picture.py benchmarks/results/castle_cameras.png
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    args = ap.parse_args(argv)
    import cv2

    from benchmarks.camera_solve import castle_scenes, pair_errors, working_copies
    from iris_runtime.camera_plot import align_poses, draw_cameras
    from iris_runtime.cameras import solve_cameras
    cv2.setNumThreads(1)
    panels = []
    for scene in castle_scenes():
        if not scene.name.startswith("castle 1-36"):
            continue
        photos = working_copies(scene.photos)
        s = solve_cameras(photos, (0.1, 1.0))
        posed = s.posed
        truth = np.linalg.inv(scene.world_from_cam[0]) @ scene.world_from_cam
        aligned, _ = align_poses(s.world_from_cam[posed], truth[posed])
        e = pair_errors(s.world_from_cam, scene.world_from_cam)
        H, W = s.image_size
        title = (f"{scene.name}, solved at {W}x{H}: {posed.sum()}/{len(posed)} posed, "
                 f"RPA@5 {np.mean(e < 5):.2f}, fx/W {s.focal / W:.3f} (true 1.094)")
        panels.append(draw_cameras(aligned, s.K, reference=truth[posed],
                                   reference_focal=scene.focal, size=(480, 640),
                                   names=("solved", "true"), title=title))
        print(title)
    from PIL import Image
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(panels, axis=1)).save(args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The README's figure: a 256x256 render beside the photos it was made from.

    python scripts/readme_figure.py out/model -o docs/images/render256.png

The quickstart's scene (samples/heldout-1000003-256): frames 0 2 3 5 7 are the references
(encoded at their 256x256, the model's default cameras), frame 1 is located against them and
rendered at 256x256 with the default quality; beside it the same pose rendered at the model's
64x64 and scaled up (bicubic), and the photo of frame 1 itself (never seen by the model). PSNR
against that photo above each render.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, ImageDraw

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from iris_runtime import IrisRuntime  # noqa: E402
from iris_runtime.images import load_image  # noqa: E402

SCENE = REPO / "samples" / "heldout-1000003-256"
REFERENCES, TARGET = (0, 2, 3, 5, 7), 1


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean((a.astype(np.float64) / 255 - b / 255.0) ** 2)))


def _label(tile: np.ndarray, text: str) -> np.ndarray:
    img = Image.fromarray(tile)
    ImageDraw.Draw(img).rectangle([0, 0, 255, 15], fill=(0, 0, 0))
    ImageDraw.Draw(img).text((4, 2), text, fill=(255, 255, 255))
    return np.asarray(img)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model_dir")
    ap.add_argument("-o", "--out", type=Path, default=REPO / "docs" / "images" / "render256.png")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    rt = IrisRuntime(args.model_dir, threads=args.threads)
    photos = [load_image(str(p)) for p in sorted(SCENE.glob("frame_*.png"))]
    scene = rt.encode([photos[i] for i in REFERENCES])
    pose = rt.locate(scene, photos[TARGET])
    sharp = rt.render(scene, pose, height=256, width=256)
    small = rt.render(scene, pose)
    up = np.clip(cv2.resize(small.astype(np.float32), (256, 256), interpolation=cv2.INTER_CUBIC),
                 0, 255).astype(np.uint8)
    truth = photos[TARGET]
    top = np.concatenate([_label(photos[i], f"reference photo {i}") for i in REFERENCES], axis=1)
    gap = np.full((256, 256, 3), 255, np.uint8)
    bottom = np.concatenate([
        _label(sharp, f"render 256, {rt.default_quality}: {_psnr(sharp, truth):.2f} dB"),
        _label(up, f"64x64 render, bicubic: {_psnr(up, truth):.2f} dB"),
        _label(truth, f"photo {TARGET} (not seen)"), gap, gap], axis=1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate([top, bottom], axis=0)).save(args.out, optimize=True)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

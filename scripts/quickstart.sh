#!/usr/bin/env bash
# The main job on a fresh machine: set up .venv, export the shipped default model to ONNX, and run
# the torch-free runtime on a held-out sample scene (cameras, novel views, a path video, depth).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
MODEL=${IRIS_MODEL:-models/iris-tiny-rgb.pt}
SCENE=${IRIS_SCENE:-samples/heldout-1000003-256}
SIZE=${IRIS_SIZE:-256x256}
OUT=${IRIS_OUT:-out}

# Run "$@", printing a line every 10 s while it runs silently (pip unpacks torch for a minute or
# more); its exit status is the step's.
with_heartbeat() {
  local what=$1; shift
  "$@" &
  local pid=$! start=$SECONDS next=$((SECONDS + 10))
  while kill -0 "$pid" 2>/dev/null; do
    sleep 1
    if [ "$SECONDS" -ge "$next" ]; then
      echo "   ... $what ($((SECONDS - start)) s)"
      next=$((next + 10))
    fi
  done
  wait "$pid"
}

if [ ! -x .venv/bin/python ]; then
  echo "== setting up .venv (torch pinned to the CPU build: an unpinned torch pulls a CUDA build)"
  $PY -m venv .venv
  with_heartbeat "installing torch 2.13.0 (CPU)" \
    .venv/bin/pip install -q --disable-pip-version-check torch==2.13.0
  with_heartbeat "installing iris-nvs[train]" \
    .venv/bin/pip install -q --disable-pip-version-check -e ".[train]"
fi

echo "== 1/2 export $MODEL -> $OUT/model (two ONNX graphs + iris.json, validated against torch)"
.venv/bin/iris-export "$MODEL" "$OUT/model" --force

echo "== 2/2 render $SCENE with the torch-free runtime"
# Re-render frames 1, 4 and 6 from their poses, plus a 24-frame orbit video, at the photos'
# 256x256 (the model sees 64x64; the colour comes from the photos at their size). The cameras are the
# manifest's default: the camera head's refined on the photos into the terms of the solve the
# renderer was trained with (docs/CAMERAS.md); IRIS_CAMERAS=solve runs the solve itself,
# IRIS_CAMERAS=model takes the head's as they are.
.venv/bin/iris-render "$OUT/model" "$SCENE"/frame_*.png -o "$OUT/render" \
  --view 1 --view 4 --view 6 --orbit 24 --size "$SIZE" ${IRIS_CAMERAS:+--cameras "$IRIS_CAMERAS"}
echo
echo "outputs: $OUT/model (graphs + manifest), $OUT/render (PNGs, depth, orbit.mp4, transforms.json, colmap/)"

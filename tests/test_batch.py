"""iris-batch: every scene folder's orbit, serially and on a local Ray cluster, byte for byte the
same, and the same as iris-render --orbit; a broken scene folder reported and left without output.

The commands run as subprocesses (as an operator runs them); the Ray run starts a local cluster
(``ray.init`` on this machine's CPUs, 2 on CI) with two actors for three scenes, so one actor
renders two scenes on one model load.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PHOTOS = sorted((REPO / "samples" / "heldout-1000003").glob("frame_*.png"))
ORBIT = ["--orbit", "2", "--size", "16x16"]


def _run(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, "OMP_NUM_THREADS": "1"})


def _files(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    """Three scene folders: two good ones and one holding an unreadable photo."""
    root = tmp_path_factory.mktemp("scenes")
    for name, photos in (("alpha", PHOTOS[0:3]), ("beta", PHOTOS[3:6])):
        (root / name).mkdir()
        for p in photos:
            shutil.copy(p, root / name / p.name)
    (root / "broken").mkdir()
    shutil.copy(PHOTOS[6], root / "broken" / PHOTOS[6].name)
    (root / "broken" / "frame_99.png").write_bytes(b"this is not a PNG")
    (root / "alpha" / "notes.txt").write_text("not a photo: ignored")
    return root


@pytest.fixture(scope="module")
def serial(model_dir, scenes, tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("serial") / "out"
    return out, _run("-m", "iris_runtime.batch", str(model_dir), str(scenes), "-o", str(out),
                     *ORBIT)


def _check_outcome(out: Path, proc: subprocess.CompletedProcess):
    assert proc.returncode == 1, proc.stderr                # one scene failed
    assert "broken: FAILED: ImageError: broken/frame_99.png" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert sorted(p.name for p in out.iterdir()) == ["alpha", "batch.json", "beta"]  # no partial
    report = json.loads((out / "batch.json").read_text())
    assert report["failed"] == ["broken"]
    assert {s["scene"]: s["ok"] for s in report["scenes"]} == {"alpha": True, "beta": True,
                                                               "broken": False}
    return report


def test_serial_batch_equals_iris_render_and_skips_a_broken_scene(serial, scenes, model_dir,
                                                                   tmp_path):
    out, proc = serial
    _check_outcome(out, proc)
    files = _files(out / "alpha")
    assert {"orbit_0000.png", "orbit_0001.png", "orbit.mp4", "orbit_poses.json",
            "transforms.json", "cameras.png", "colmap/images.txt", "inputs/000.png"} <= set(files)
    # The same as iris-render --orbit on the folder's photos, byte for byte.
    single = tmp_path / "single"
    photos = sorted(str(p) for p in (scenes / "alpha").glob("*.png"))
    r = _run("-m", "iris_runtime.cli", str(model_dir), *photos, "-o", str(single), *ORBIT, "-q",
             "--threads", "1")
    assert r.returncode == 0, r.stderr
    assert _files(single) == files


def test_ray_batch_is_byte_identical_to_the_serial_run(serial, scenes, model_dir, tmp_path):
    pytest.importorskip("ray", reason="ray is not installed (pip install 'iris-nvs[batch]')")
    out_serial, _ = serial
    out = tmp_path / "ray"
    proc = _run("-m", "iris_runtime.batch", str(model_dir), str(scenes), "-o", str(out), *ORBIT,
                "--ray", "local", "--actors", "2")
    report = _check_outcome(out, proc)
    for scene in ("alpha", "beta"):
        ray_files, serial_files = _files(out / scene), _files(out_serial / scene)
        assert sorted(ray_files) == sorted(serial_files)
        pngs = [k for k in serial_files if k.endswith(".png")]
        assert len(pngs) >= 5
        for name in serial_files:                          # the PNGs, and every other file
            assert ray_files[name] == serial_files[name], (scene, name)
    assert report["ray"] == "local"
    workers = {s["worker"] for s in report["scenes"]}
    assert len(workers) <= 2                               # 3 scenes on 2 actors: one reused


def test_existing_outputs_need_force(serial, scenes, model_dir):
    out, _ = serial
    before = _files(out / "alpha")
    proc = _run("-m", "iris_runtime.batch", str(model_dir), str(scenes), "-o", str(out), *ORBIT)
    assert proc.returncode == 2 and "--force" in proc.stderr
    assert _files(out / "alpha") == before
    proc = _run("-m", "iris_runtime.batch", str(model_dir), str(scenes), "-o", str(out), *ORBIT,
                "--force", "-q")
    assert proc.returncode == 1 and _files(out / "alpha") == before       # replaced, same bytes
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_bad_arguments_exit_2(model_dir, tmp_path):
    for args, text in (([str(model_dir), str(tmp_path / "none")], "not a directory"),
                       ([str(tmp_path / "nomodel"), str(REPO / "samples")], "nomodel")):
        proc = _run("-m", "iris_runtime.batch", *args, "-o", str(tmp_path / "o"), "--orbit", "2")
        assert proc.returncode == 2 and text in proc.stderr and "Traceback" not in proc.stderr

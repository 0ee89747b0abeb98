"""The layout a maintainer relies on: no file of iris_train over 500 lines, no import circle between
the training loop and the pseudo-poses, and benchmarks/ never importing scripts/ (the scripts that
import benchmarks/ are listed, each with its reason), and no machine path in a tracked text file."""
from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MAX_LINES = 500

#: The scripts that import benchmarks/, and why. The shared code lives in benchmarks/ only
#: (``camera_solve``: the camera-solve datasets and scoring; ``camera_settings``: the ``--set``
#: settings; ``refine_cost``: the refinement's measurement); these scripts are studies run on it
#: whose commands docs/CAMERAS.md documents under scripts/.
SCRIPTS_ON_BENCHMARKS = {
    "camera_study.py": "the camera solve with a setting changed, on camera_solve's datasets",
    "camera_picture.py": "draws camera_solve's castle scene as the solve poses it",
    "salvage_grow_probe.py": "runs refine_cost's measurement with a variant of the salvage",
}


def _imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports, anywhere in the file (absolute names; relative imports as
    '.NAME')."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            out.add("." * node.level + (node.module or ""))
    return out


def _top(name: str) -> str:
    return name.split(".")[0]


def test_no_iris_train_file_exceeds_the_limit():
    long = {str(p.relative_to(REPO)): n for p in (REPO / "iris_train").rglob("*.py")
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"over {MAX_LINES} lines: {long}"


def test_pseudo_poses_does_not_import_the_training_loop():
    imported = _imported_modules(REPO / "iris_train" / "pseudo_poses.py")
    assert not imported & {".train", "iris_train.train"}, imported


def test_train_and_pseudo_poses_import_in_either_order():
    for first, second in (("train", "pseudo_poses"), ("pseudo_poses", "train")):
        code = f"import iris_train.{first}, iris_train.{second}"
        out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                             text=True)
        assert out.returncode == 0, out.stderr


def test_benchmarks_never_import_scripts():
    for path in sorted((REPO / "benchmarks").rglob("*.py")):
        assert "scripts" not in {_top(m) for m in _imported_modules(path)}, path


def test_only_the_listed_scripts_import_benchmarks():
    importing = {p.name for p in (REPO / "scripts").glob("*.py")
                 if "benchmarks" in {_top(m) for m in _imported_modules(p)}}
    assert importing == set(SCRIPTS_ON_BENCHMARKS)


#: A path on the machine a file was written on (a home, the workplace's root): never in a file
#: of the repository, which names data by set or by a path relative to the repository.
MACHINE_PATH = re.compile(r"(?<![\w.~-])/(?:work|root|home)/[\w.-]")


def test_no_tracked_text_file_holds_a_machine_path():
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True)
    if listed.returncode != 0:
        pytest.skip("not a git checkout")
    found = []
    for name in listed.stdout.decode().split("\0"):
        path = REPO / name
        if not name or not path.is_file() or path.stat().st_size > 20_000_000:
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:                       # binary (checkpoints, images, npz)
            continue
        text = data.decode("utf-8", errors="replace")
        found += [f"{name}:{i}" for i, line in enumerate(text.splitlines(), 1)
                  if MACHINE_PATH.search(line)]
    assert not found, f"machine paths: {found[:20]}"

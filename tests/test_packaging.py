"""The runtime is torch-free: by its imports and by its declared dependencies."""
from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_runtime_imports_and_renders_with_torch_blocked():
    # sys.modules["torch"] = None makes every `import torch` raise ImportError in that process.
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "import iris_runtime, iris_runtime.cli, iris_runtime.geometry, iris_runtime.images\n"
        "import iris_runtime.camera_io, iris_runtime.manifest, iris_runtime.fileio\n"
        "import iris_runtime.io_spec\n"
        "assert 'torch' not in [m for m, v in sys.modules.items() if v is not None]\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_runtime_dependencies_exclude_torch():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    deps = " ".join(project["dependencies"]).lower()
    assert "torch" not in deps and "onnx>" not in deps
    for name in ("numpy", "onnxruntime", "pillow", "opencv-contrib-python-headless"):
        assert name in deps
    # torch only ever pinned (an unpinned torch resolves to a multi-GB CUDA build).
    assert "torch==2.13.0" in project["optional-dependencies"]["train"]


def test_no_torch_import_in_runtime_sources():
    for path in (REPO / "iris_runtime").rglob("*.py"):
        for line in path.read_text().splitlines():
            stripped = line.strip()
            assert not stripped.startswith(("import torch", "from torch")), f"{path}: {line}"

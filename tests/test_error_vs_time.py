"""benchmarks/error_vs_time.py: its report and targets reproduce the committed results from the
committed JSON, its row names are the committed ones, its children run as real modules."""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from benchmarks import error_vs_time
from benchmarks.evt import child, measure, report, rows as R, targets

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"


@pytest.fixture(scope="module")
def committed() -> dict:
    return json.loads((RESULTS / report.JSON_NAME).read_text())


def test_report_reproduces_committed_markdown(committed):
    # README.md and docs/PERFORMANCE.md quote this file: its layout is part of the contract.
    assert report.markdown(committed) == (RESULTS / report.MARKDOWN_NAME).read_text()


def test_targets_reproduce_committed(committed):
    assert targets.evaluate_targets(committed) == committed["targets"]


def test_peak_rows_reproduce_committed(committed):
    rows = measure.peak_rows(committed["knobs"]["rows"], committed["peak"]["matmul"]["gflops"])
    assert rows == committed["peak"]["rows"]


def test_row_names_are_the_committed_ones(committed):
    names = [r["name"] for r in committed["knobs"]["rows"]]
    assert names[:6] == [R.TORCH_EAGER, R.TORCH_TCMALLOC, R.EXACT, R.EXACT_2_WORKERS,
                         R.EXACT_NO_CULLING, R.EXACT_NO_SCENE_CACHE]
    assert names[6:] == [k.name for k in R.KNOB_GRID]
    assert [r["group"] for r in committed["knobs"]["rows"][6:]] == [k.group for k in R.KNOB_GRID]
    assert set(R.PEAK_ROWS) >= {r["name"] for r in committed["peak"]["rows"]}


def test_targets_skip_what_did_not_run():
    assert targets.evaluate_targets({}) == []
    # The peak part without the knobs part has no rows to check (used to raise StopIteration).
    assert targets.evaluate_targets({"peak": {"matmul": {"gflops": 1.0}, "rows": []}}) == []


def test_quick_fills_only_defaults():
    args = error_vs_time.parse_args(["--quick", "--runs", "2"])
    assert args.runs == 2 and args.size == error_vs_time.QUICK["size"]
    assert args.scaling == [(4, 1), (16, 1)] and args.memory_quality == ["balanced", "exact@16"]
    assert "--quick" in args.note
    full = error_vs_time.parse_args([])
    assert full.size == 64 and full.scaling == list(R.SCALING) and not full.quick


def test_children_are_module_commands():
    cmd = child.command("memory", model_dir=Path("m"), quality="balanced", threads=1)
    assert cmd[1:4] == ["-m", "benchmarks.evt.child", "memory"]
    assert cmd[4:6] == ["--model-dir", str(Path("m").resolve())]
    assert child.environment()["PYTHONPATH"].split(":")[0] == str(REPO)


def test_memory_child_renders_torch_free(model_dir, tmp_path):
    size = json.loads((Path(model_dir) / "iris.json").read_text())["image_size"]
    images = np.random.default_rng(0).integers(0, 256, (16, *size, 3), dtype=np.uint8)
    np.save(tmp_path / "refs.npy", images)
    cmd = child.command("memory", model_dir=Path(model_dir), quality="balanced", threads=1,
                        size=8, images=tmp_path / "refs.npy", workers=1)
    proc = subprocess.run(cmd, env=child.environment(), cwd=tmp_path, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    row = json.loads(proc.stdout.strip().splitlines()[-1])
    assert row["quality"] == "balanced" and row["size"] == [8, 8] and row["finite"]
    assert row["peak_rss_mb"] >= row["rss_after_encode_mb"] >= row["rss_before_mb"] > 0

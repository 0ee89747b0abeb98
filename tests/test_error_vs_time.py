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
    # docs/PERFORMANCE.md quotes this file: its layout is part of the contract.
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
    # The grid has grown since the committed run (coarse-to-fine rows): its rows are the grid's,
    # in the grid's order, with the grid's groups.
    grid = [(k.name, k.group) for k in R.KNOB_GRID]
    run = [(r["name"], r["group"]) for r in committed["knobs"]["rows"][6:]]
    assert run == [g for g in grid if g[0] in set(names)]
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
    assert args.sizing_sizes == [8, 16] and args.sizing_views == [4, 8] and args.fps_poses == 2
    full = error_vs_time.parse_args([])
    assert full.size == 64 and full.scaling == list(R.SCALING) and not full.quick
    assert full.sizing_sizes == [64, 128, 256] and full.sizing_views == [4, 8, 16]
    assert "sizing" in error_vs_time.PARTS


def test_report_and_targets_of_the_new_sections(committed):
    """The coarse-to-fine rows, the adaptive target and the sizing section appear when a run has
    them (the committed run predates them: the tests above)."""
    import copy
    res = copy.deepcopy(committed)
    rows = res["knobs"]["rows"]
    exact = next(r for r in rows if r["name"] == R.EXACT)
    ad = dict(exact, name=R.PRESET_ADAPTIVE, group=R.PRESET_GROUP,
              s_per_frame=exact["s_per_frame"] / 5, psnr_gt=exact["psnr_gt"] - 0.05,
              psnr_vs_full=35.0, refined_fraction=0.12, windowed_fraction=0.0,
              kept_sample_fraction=1.0, note="")
    every = dict(ad, name=R.REFINE_EVERY, group=R.REFINE_GROUP, max_abs_vs_full=2e-7,
                 s_per_frame=exact["s_per_frame"] * 1.07, refined_fraction=1.0)
    rows += [every, ad]
    res["sizing"] = {"seed": 1000000, "frames": 17, "presets": ["exact", "adaptive"],
                     "workers": 2, "threads": 2, "rows": [
                         {"views": v, "size": z, "preset": p, "s_per_frame": 0.1 * v * z / 64,
                          "encode_s": 0.05 * v, "psnr_vs_exact": 100.0 if p == "exact" else 35.0}
                         for p in ("exact", "adaptive") for v in (4, 8) for z in (64, 128)],
                     "fps": [{"preset": "exact", "views": 8, "size": 64, "poses": 24,
                              "seconds": 30.0, "fps": 0.8, "encode_s": 0.1}]}
    text = report.markdown(res)
    assert "| refine 1/4, every pixel | 100.0% |" in text
    assert "| preset adaptive | 12.0% | 0.0% | 100.0% | 5.00x |" in text
    assert "## Server sizing" in text and "| adaptive | 8 | 0.40 | 0.800 | 1.600 | 35.00 |" in text
    assert "| exact | 0.80 | 30.00 |" in text
    got = {t["target"]: t for t in targets.evaluate_targets(res)}
    t = next(v for k, v in got.items() if k.startswith("adaptive preset >= 4x"))
    assert t["met"] and t["measured"].startswith("5.00x") and "-0.050 dB" in t["measured"]
    t = next(v for k, v in got.items() if k.startswith("exact knobs unchanged"))
    assert t["met"] and "refine every pixel vs full: max abs 2.0e-07" in t["measured"]
    ad["psnr_gt"] = exact["psnr_gt"] - 0.2                  # too lossy: missed, whatever the speed
    got = targets.evaluate_targets(res)
    assert not next(t for t in got if t["target"].startswith("adaptive preset"))["met"]


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

"""scripts/eval_by_kind.py: per-kind means of an iris-eval result against a hand count."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def load_script():
    spec = importlib.util.spec_from_file_location("eval_by_kind", ROOT / "scripts" / "eval_by_kind.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def scene(name: str, psnr: float, rho: float) -> dict:
    return {"name": name, "model": {"psnr": psnr, "depth_spearman": rho, "ssim": 0.5}}


RESULT = {"rand": {"scenes": [scene("walk", 20.0, 0.5), scene("orbit", 24.0, 0.7),
                              scene("walk", 22.0, 0.7), scene("forward", 27.0, 0.8)]},
          "seq": {"scenes": [scene("walk", 10.0, 0.1)]}}


def test_means_per_kind_and_overall():
    table = load_script().by_kind(RESULT["rand"], ["psnr", "depth_spearman"])
    assert table["walk"] == pytest.approx({"psnr": 21.0, "depth_spearman": 0.6, "n": 2})
    assert table["orbit"]["n"] == 1 and table["forward"]["psnr"] == 27.0
    assert table["all"] == pytest.approx({"psnr": 23.25, "depth_spearman": 0.675, "n": 4})


def test_table_reads_the_chosen_order(tmp_path, capsys):
    path = tmp_path / "run.json"
    path.write_text(json.dumps(RESULT))
    load_script().main([str(path), "--order", "seq"])
    out = capsys.readouterr().out
    assert "| run | 10.00 / 0.100 | 10.00 / 0.100 |" in out and "all (1)" in out

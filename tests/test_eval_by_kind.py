"""scripts/eval_by_kind.py: per-kind means of an iris-eval result against a hand count."""
from __future__ import annotations

import json

import pytest

from . import conftest


def load_script():
    return conftest.load_script("eval_by_kind")


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

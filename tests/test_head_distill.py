"""scripts/head_distill.py: a short run trains the encoder and the camera head only, on the
solve's cameras, and writes a loadable checkpoint and a log with held-out scores."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "models" / "iris-tiny-rgb.pt"


def _script():
    spec = importlib.util.spec_from_file_location("head_distill", ROOT / "scripts" / "head_distill.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.skipif(not SHIPPED.exists(), reason="needs the shipped checkpoint")
def test_head_distill_trains_the_encoder_and_head_only(tmp_path, monkeypatch):
    from iris_train import load_model
    monkeypatch.setenv("IRIS_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "run"
    assert _script().main(["--out", str(out), "--classic", "2", "--steps", "2", "--batch", "1",
                           "--eval-every", "1", "--heldout-scenes", "1",
                           "--camera-head", "correlation"]) == 0
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [e["step"] for e in log] == [0, 1, 2]
    assert set(log[-1]["train"]) == {"solve_rot", "solve_trans", "solve_focal"}
    assert 0.0 <= log[-1]["heldout"]["rpa@15"] <= 1.0
    trained, shipped = load_model(out / "last.pt"), load_model(SHIPPED)
    assert trained.cfg.camera_head == "correlation"
    before, after = shipped.state_dict(), trained.state_dict()
    for name in ("field", "renderer"):
        for key, value in getattr(shipped, name).state_dict().items():
            assert torch.equal(value, after[f"{name}.{key}"]), key
    moved = [k for k in before if k.startswith("encoder.") and not torch.equal(before[k], after[k])]
    assert moved, "the encoder did not train"

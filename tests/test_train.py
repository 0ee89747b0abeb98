"""iris-train: the loop runs, logs, checkpoints, resumes exactly, and runs under torchrun (DDP/gloo)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from iris_train import load_model, read_checkpoint  # noqa: E402
from iris_train.train import TrainConfig, draw_batch, lr_factor, train  # noqa: E402
from iris_train.config import preset  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


@dataclass
class FakeScene:
    images: np.ndarray


def fake_scenes(n=3, seed=0):
    rng = np.random.default_rng(seed)
    return [FakeScene(rng.integers(0, 256, (8, 64, 64, 3), dtype=np.uint8)) for _ in range(n)]


SMALL = dict(scenes_per_step=1, rays_per_scene=32, views_min=3, views_max=4, warmup=2, teacher_weight=0.0,
             teacher_translation_weight=0.0, teacher_focal_weight=0.0,
             log_every=1, ckpt_every=2)


def test_lr_schedule_warms_up_then_decays():
    cfg = TrainConfig(steps=100, warmup=10, lr=1.0, min_lr_ratio=0.1)
    f = [lr_factor(s, cfg) for s in range(100)]
    assert f[0] == pytest.approx(0.1) and f[9] == pytest.approx(1.0)
    assert all(a >= b for a, b in zip(f[10:], f[11:]))         # monotone decay after warm-up
    assert f[-1] == pytest.approx(0.1, abs=1e-3)


def test_draw_batch_splits_views_into_disjoint_reference_and_target_sets():
    cfg = TrainConfig(**SMALL)
    images, ref, tgt, pixels, depths, teacher, pose_batch = draw_batch(fake_scenes(), cfg, preset("tiny"),
                                                  np.random.default_rng(0))
    assert images.dtype == torch.float32 and 0 <= float(images.min()) and float(images.max()) <= 1
    for r, t, p, d in zip(ref, tgt, pixels, depths):
        assert len(r) >= 1 and len(t) >= 1 and not set(r.tolist()) & set(t.tolist())
        assert len(r) + len(t) == images.shape[1]
        assert d.shape == (p.numel(), 64)
        assert bool(((d >= 0.1) & (d <= 1.0)).all())


def test_train_logs_checkpoints_and_resumes_exactly(tmp_path):
    scenes = fake_scenes()
    cfg = TrainConfig(steps=4, **SMALL)
    # Run A: 4 steps straight. Run B: 2 steps, stop, resume for the last 2.
    train(cfg, tmp_path / "a", scenes=scenes, threads=1)
    train(TrainConfig(steps=4, **SMALL), tmp_path / "b", scenes=scenes, threads=1, max_seconds=0.0)
    assert read_checkpoint(tmp_path / "b" / "last.pt")["step"] == 1   # stopped after one step
    train(cfg, tmp_path / "b", scenes=scenes, threads=1, resume=True)
    log = [json.loads(line) for line in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [0, 1, 2, 3]
    assert {"step", "loss", "psnr", "lr", "time"} <= set(log[0])
    a = read_checkpoint(tmp_path / "a" / "last.pt")
    b = read_checkpoint(tmp_path / "b" / "last.pt")
    assert a["step"] == b["step"] == 4 and a["config"] == b["config"]
    model = load_model(tmp_path / "a" / "last.pt")
    assert not model.training
    # The resumed run is the same run: same batches (one generator per step), same optimiser state.
    for k in a["model"]:
        torch.testing.assert_close(a["model"][k], b["model"][k], rtol=0, atol=1e-6, msg=k)
    # ... and training did something.
    torch.manual_seed(cfg.seed)
    from iris_train import build_model
    fresh = build_model(preset("tiny")).state_dict()
    assert any(not torch.equal(fresh[k], a["model"][k]) for k in fresh)


def test_torchrun_two_processes(tmp_path):
    """DistributedDataParallel with gloo on CPU: two processes run the same loop."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--master_port=29517",
           "-m", "iris_train.train", "--out", str(tmp_path / "ddp"), "--steps", "2",
           "--train-scenes", "2", "--scenes-per-step", "1", "--rays-per-scene", "16",
           "--views-min", "3", "--views-max", "3", "--warmup", "1", "--log-every", "1", "--threads", "1"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    log = [json.loads(x) for x in (tmp_path / "ddp" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [0, 1]
    assert read_checkpoint(tmp_path / "ddp" / "last.pt")["step"] == 2

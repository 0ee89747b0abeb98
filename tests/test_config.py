"""TrainConfig.from_dict: an unknown key is an error naming it, retired keys are mapped or dropped
by a list, and the config of every committed checkpoint loads."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from iris_runtime.errors import InputError  # noqa: E402
from iris_train import config  # noqa: E402
from iris_train.config import ModelConfig, TrainConfig  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CHECKPOINTS = sorted([*REPO.glob("models/*.pt"), *REPO.glob("models/experiments/*.pt")])


def test_train_config_round_trips():
    cfg = TrainConfig(steps=7, render_cameras="epipolar", colour_size=128, freeze_cameras=True)
    assert TrainConfig.from_dict(dataclasses.asdict(cfg)) == cfg


def test_missing_train_config_fields_take_their_defaults():
    assert TrainConfig.from_dict({"steps": 3}) == TrainConfig(steps=3)


def test_an_unknown_train_config_key_is_an_error_naming_it():
    with pytest.raises(InputError, match="sceens_per_step") as info:
        TrainConfig.from_dict({**dataclasses.asdict(TrainConfig()), "sceens_per_step": 4})
    assert isinstance(info.value, ValueError)


def test_retired_train_config_keys_are_mapped_or_dropped(monkeypatch):
    monkeypatch.setattr(config, "RETIRED_TRAIN_KEYS", {"n_steps": "steps", "old_knob": None})
    assert TrainConfig.from_dict({"n_steps": 5, "old_knob": 1.0}) == TrainConfig(steps=5)
    # The field under its new name wins over the old one.
    assert TrainConfig.from_dict({"n_steps": 5, "steps": 6}).steps == 6
    with pytest.raises(InputError, match="other_knob"):
        TrainConfig.from_dict({"old_knob": 1.0, "other_knob": 2})


def test_every_retired_key_maps_to_a_field_or_none():
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    for old, new in config.RETIRED_TRAIN_KEYS.items():
        assert old not in fields and (new is None or new in fields)


def test_committed_checkpoints_are_found():
    assert any(p.name == "iris-tiny-rgb.pt" for p in CHECKPOINTS)


@pytest.mark.parametrize("path", CHECKPOINTS, ids=lambda p: str(p.relative_to(REPO)))
def test_every_committed_checkpoint_config_loads(path):
    payload = torch.load(path, weights_only=True, map_location="cpu")
    ModelConfig.from_dict(payload["config"])
    if "train_config" in payload:
        cfg = TrainConfig.from_dict(payload["train_config"])
        assert {k: v for k, v in dataclasses.asdict(cfg).items()
                if k in payload["train_config"]} == payload["train_config"]

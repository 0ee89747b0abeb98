"""``scripts/ship_checkpoint.py --blend-sharpness G``: the colour blend of the shipped model is the
source's softmax at temperature 1/G (checked against the source's own logits), the checkpoint
records G, and a value that is not > 0 or a model without a colour blend is refused."""
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from iris_train import load_model
from iris_train.layers import masked_softmax
from iris_train.model import read_checkpoint, save_checkpoint
from tests.conftest import random_model

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = [sys.executable, str(ROOT / "scripts" / "ship_checkpoint.py")]


def test_blend_sharpness_is_the_blend_at_another_temperature(tmp_path):
    source = random_model("tiny-rgb")
    save_checkpoint(tmp_path / "s.pt", source)
    subprocess.run([*SCRIPT, str(tmp_path / "s.pt"), str(tmp_path / "g.pt"),
                    "--blend-sharpness", "2.5"], check=True, cwd=ROOT, capture_output=True)
    sharp = load_model(tmp_path / "g.pt").eval()
    assert read_checkpoint(tmp_path / "g.pt")["blend_sharpness"] == 2.5
    torch.manual_seed(0)
    R, S, W = 7, 12, source.cfg.field_width
    f, positions = torch.randn(R, S, W), torch.rand(R, S, 3)
    directions = torch.nn.functional.normalize(torch.randn(R, 3), dim=-1)
    mask = (torch.rand(R, S) > 0.3).float()
    colours = torch.rand(R, S, 3)
    with torch.no_grad():
        _, w = sharp.renderer(f, positions, directions, mask, colours=colours)
        # The source's logits, through the same transformer (its weights are the source's).
        h = source.renderer.ray_transformer(f, positions, directions, mask, False)[0]
        logits = source.renderer.sample_logit(source.renderer.norm(h))[..., 0]
    want = masked_softmax(2.5 * logits, mask) * mask.amax(-1, keepdim=True)
    assert torch.allclose(w, want, atol=1e-6)
    rest = {k for k in sharp.state_dict() if not k.startswith("renderer.sample_logit.")}
    assert all(torch.equal(sharp.state_dict()[k], source.state_dict()[k]) for k in rest)


@pytest.mark.parametrize("preset, value, message", [
    ("tiny-rgb", "0", "finite number > 0"),
    ("tiny-rgb", "nan", "finite number > 0"),
    ("tiny", "2", "explicit_rgb"),
])
def test_blend_sharpness_refuses(tmp_path, preset, value, message):
    save_checkpoint(tmp_path / "s.pt", random_model(preset))
    run = subprocess.run([*SCRIPT, str(tmp_path / "s.pt"), str(tmp_path / "g.pt"),
                          "--blend-sharpness", value], cwd=ROOT, capture_output=True, text=True)
    assert run.returncode != 0 and message in run.stderr
    assert not (tmp_path / "g.pt").exists()

"""scripts/resize_checkpoint.py: a model carried to k times its image size sees, through its
encoder, exactly what the original sees on the k x k block-averaged image."""
from __future__ import annotations


import numpy as np
import pytest

from . import conftest

torch = pytest.importorskip("torch")

from iris_train import build_model, load_model  # noqa: E402
from iris_train.config import preset  # noqa: E402

pytestmark = pytest.mark.torch


def _script():
    return conftest.load_script("resize_checkpoint")


@pytest.mark.parametrize("factor", [2, 3])
def test_encoder_equals_original_on_block_average(factor):
    torch.manual_seed(0)
    small = build_model(preset("tiny-rgb")).eval()
    cfg, state = _script().resize_state(small.cfg, small.state_dict(), factor)
    big = build_model(cfg).eval()
    big.load_state_dict(state)
    assert (cfg.image_height, cfg.patch_size) == (64 * factor, 8 * factor)
    assert cfg.feature_grid == small.cfg.feature_grid
    rng = np.random.default_rng(1)
    image = rng.random((1, 3, 3, 64 * factor, 64 * factor)).astype(np.float32)
    averaged = image.reshape(1, 3, 3, 64, factor, 64, factor).mean(axis=(4, 6))
    with torch.no_grad():
        ref = small.encode_batch(torch.from_numpy(averaged))
        out = big.encode_batch(torch.from_numpy(image))
    for a, b in zip(ref, out):
        assert a.shape == b.shape
        torch.testing.assert_close(b, a, atol=1e-5, rtol=0)


def test_cli_writes_a_loadable_checkpoint(tmp_path):
    torch.manual_seed(0)
    model = build_model(preset("tiny-rgb"))
    from iris_train.model import save_checkpoint
    save_checkpoint(tmp_path / "a.pt", model, step=7)
    import sys
    script = _script()
    argv = sys.argv
    sys.argv = ["resize_checkpoint", str(tmp_path / "a.pt"), str(tmp_path / "b.pt"), "--factor", "2"]
    try:
        script.main()
    finally:
        sys.argv = argv
    loaded = load_model(tmp_path / "b.pt")
    assert loaded.cfg.image_height == 128 and loaded.cfg.patch_size == 16


@pytest.mark.parametrize("factor", [0, -1, 1.5, True])
def test_bad_factor_is_refused(factor):
    model = build_model(preset("tiny-rgb"))
    with pytest.raises(ValueError, match="factor"):
        _script().resize_state(model.cfg, model.state_dict(), factor)

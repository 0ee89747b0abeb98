"""Finer field maps (``ModelConfig.map_scale``, ``encoder.FineFeatures``): the config's
contract, the stem's start at the upsampled token features, the references' isolation, and a
fine-tune from a model of map scale 1. The exported graphs and the runtime are held to torch
on such a model by tests/test_runtime.py (``pair``'s "tiny-rgb-fine")."""
from __future__ import annotations

import dataclasses

import pytest

torch = pytest.importorskip("torch")
F = torch.nn.functional

from iris_runtime.errors import InputError                     # noqa: E402
from iris_train.config import preset                            # noqa: E402
from iris_train.model import build_model                        # noqa: E402
from iris_train.train import load_init_weights                  # noqa: E402

from .conftest import random_model                              # noqa: E402

pytestmark = pytest.mark.torch


@pytest.fixture(autouse=True)
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("scale, grid, convs", [(1, (8, 8), None), (2, (16, 16), 2), (4, (32, 32), 1)])
def test_field_grid_and_stem_stride(scale, grid, convs):
    cfg = dataclasses.replace(preset("tiny-rgb"), map_scale=scale)
    assert cfg.field_grid == grid and cfg.feature_grid == (8, 8)
    model = build_model(cfg)
    if convs is None:
        assert model.fine_features is None
        return
    strides = [m.stride[0] for m in model.fine_features.stem if isinstance(m, torch.nn.Conv2d)]
    assert strides == [2] * convs + [1]


@pytest.mark.parametrize("scale", [0, 3, 8, -2, 2.0, "2"])
def test_bad_map_scale_is_refused(scale):
    with pytest.raises(InputError, match="map_scale"):
        dataclasses.replace(preset("tiny-rgb"), map_scale=scale)


def test_fresh_stem_gives_the_upsampled_token_features():
    """The mix starts at zero: the field's features are the token features upsampled
    bilinearly, exactly, so a fine-tune starts from the coarse model's field."""
    torch.manual_seed(0)
    model = build_model(dataclasses.replace(preset("tiny-rgb"), map_scale=2)).eval()
    images = torch.rand(1, 3, 3, 64, 64)
    with torch.no_grad():
        tokens, _ = model.encoder(images)
        fine, _, _ = model.encode_batch(images)
    want = F.interpolate(tokens[0], scale_factor=2, mode="bilinear", align_corners=False)
    assert fine.shape == (1, 3, 128, 16, 16)
    assert torch.equal(fine[0], want)


def test_references_stay_isolated_from_queries():
    """The stem sees one view: a reference's field features are the same whether a query is
    present, changed or absent (bitwise; the stem's mix is non-zero here)."""
    model = random_model("tiny-rgb", map_scale=2)
    assert model.fine_features.mix.weight.abs().sum() > 0
    refs = torch.rand(1, 3, 3, 64, 64, generator=torch.Generator().manual_seed(1))
    query = torch.rand(1, 1, 3, 64, 64, generator=torch.Generator().manual_seed(2))
    is_reference = torch.tensor([True, True, True, False])
    with torch.no_grad():
        alone, _, _ = model.encode_batch(refs)
        with_query, _, _ = model.encode_batch(torch.cat([refs, query], 1), is_reference)
        changed, _, _ = model.encode_batch(torch.cat([refs, 1 - query], 1), is_reference)
    assert torch.allclose(with_query[:, :3], alone, atol=1e-5, rtol=0)
    assert torch.equal(with_query[:, :3], changed[:, :3])
    assert not torch.allclose(with_query[:, 3], changed[:, 3])


def test_fine_tune_from_a_coarse_model_starts_the_stem_fresh():
    coarse = random_model("tiny-rgb")
    payload = {"config": coarse.cfg.to_dict(), "model": coarse.state_dict()}
    fine = build_model(dataclasses.replace(coarse.cfg, map_scale=2))
    fresh = load_init_weights(fine, payload)
    assert fresh and all(k.startswith("fine_features.") for k in fresh)
    assert set(fresh) == {k for k in fine.state_dict() if k.startswith("fine_features.")}
    state = fine.state_dict()
    assert all(torch.equal(state[k], v) for k, v in coarse.state_dict().items())
    # And back: a fine checkpoint into a coarse model drops the stem.
    back = build_model(coarse.cfg)
    assert load_init_weights(back, {"config": fine.cfg.to_dict(), "model": state}) == []
    # Anything else that differs is still refused.
    other = dataclasses.replace(coarse.cfg, field_width=32, map_scale=2)
    with pytest.raises(ValueError, match="another model config"):
        load_init_weights(build_model(other), payload)


def test_a_fine_renderer_ships_with_a_coarse_models_camera_head(tmp_path):
    """``ship_checkpoint.py --camera-head-from``: the field maps' grid, the colour deviation
    input and the sampled depth range are the renderer's, so a head from a model of
    ``map_scale`` 1 without the deviation merges into a finer renderer with it and a wider range
    of the same cameras' unit (which keeps its settings and features); a renderer of another
    unit, or a model that differs in anything else, is still refused."""
    import subprocess
    import sys
    from pathlib import Path

    from iris_train import load_model
    from iris_train.model import save_checkpoint

    root = Path(__file__).resolve().parents[1]
    script = [sys.executable, str(root / "scripts" / "ship_checkpoint.py")]
    renderer = random_model("tiny-rgb", map_scale=2, colour_deviation=True,
                            camera_head="correlation", far=1.9, samples=96, median_depth=0.55)
    cameras = random_model("tiny-rgb", camera_head="correlation")
    with torch.no_grad():
        for p in cameras.camera_head.parameters():
            p.add_(0.01)
    save_checkpoint(tmp_path / "r.pt", renderer)
    save_checkpoint(tmp_path / "c.pt", cameras)
    subprocess.run([*script, str(tmp_path / "r.pt"), str(tmp_path / "m.pt"),
                    "--camera-head-from", str(tmp_path / "c.pt")], check=True, cwd=root)
    merged = load_model(tmp_path / "m.pt").eval()
    assert merged.cfg.map_scale == 2 and merged.cfg.colour_deviation and merged.cfg.camera_encoder
    assert (merged.cfg.far, merged.cfg.samples, merged.cfg.median_depth) == (1.9, 96, 0.55)
    images = torch.rand(1, 3, 3, 64, 64)
    with torch.no_grad():
        f_m, T_m, _ = merged.encode_batch(images)
        f_r, _, _ = renderer.encode_batch(images)
        _, T_c, _ = cameras.encode_batch(images)
    assert torch.equal(f_m, f_r) and torch.equal(T_m, T_c)
    other = random_model("tiny-rgb", field_width=32, camera_head="correlation")
    save_checkpoint(tmp_path / "o.pt", other)
    run = subprocess.run([*script, str(tmp_path / "r.pt"), str(tmp_path / "x.pt"),
                          "--camera-head-from", str(tmp_path / "o.pt")], cwd=root,
                         capture_output=True, text=True)
    assert run.returncode != 0 and "another model" in run.stderr
    assert not (tmp_path / "x.pt").exists()
    save_checkpoint(tmp_path / "u.pt", random_model("tiny-rgb", camera_head="correlation",
                                                    far=1.9, median_depth=0.7))
    run = subprocess.run([*script, str(tmp_path / "u.pt"), str(tmp_path / "x.pt"),
                          "--camera-head-from", str(tmp_path / "c.pt")], cwd=root,
                         capture_output=True, text=True)
    assert run.returncode != 0 and "unit differs" in run.stderr
    assert not (tmp_path / "x.pt").exists()


def test_colour_deviation_starts_at_the_model_without_it():
    """``colour_deviation``: its map starts at zero, so a fine-tune from a model without it
    renders what that model renders, bit for bit; the deviation is each view's colour minus
    the validity-weighted mean, and 0 where no view sees the sample."""
    from iris_train.latent_field import colour_deviation

    plain = random_model("tiny-rgb")
    payload = {"config": plain.cfg.to_dict(), "model": plain.state_dict()}
    model = build_model(dataclasses.replace(plain.cfg, colour_deviation=True)).eval()
    assert load_init_weights(model, payload) == ["field.deviation_to_maps.weight"]
    images = torch.rand(3, 3, 64, 64, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        a = plain.render(plain.encode(images), plain.encode(images).world_from_cam[1:2], 16, 16)
        b = model.render(model.encode(images), model.encode(images).world_from_cam[1:2], 16, 16)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    colours = torch.tensor([[[0.2, 0.4, 0.6], [0.4, 0.4, 0.0], [9.0, 9.0, 9.0]]])
    d = colour_deviation(colours, torch.tensor([[1.0, 1.0, 0.0]]))
    torch.testing.assert_close(d[0, 0], torch.tensor([-0.1, 0.0, 0.3, 0.1, 0.0, 0.3]))
    assert torch.equal(colour_deviation(colours, torch.zeros(1, 3))[..., :3], colours)
    with pytest.raises(InputError, match="colour_deviation"):
        dataclasses.replace(preset("tiny"), colour_deviation=True)


def test_map_scale_needs_a_power_of_two_stride_only_above_one():
    cfg = dataclasses.replace(preset("tiny-rgb"), image_height=72, image_width=72, patch_size=24)
    assert cfg.field_grid == (3, 3)                    # map_scale 1: any patch
    with pytest.raises(InputError, match="map_scale"):
        dataclasses.replace(cfg, map_scale=2)          # stride 12
    assert dataclasses.replace(preset("tiny-rgb"), patch_size=16).field_grid == (4, 4)
    assert dataclasses.replace(preset("tiny-rgb"), patch_size=16, map_scale=4).field_grid == (16, 16)

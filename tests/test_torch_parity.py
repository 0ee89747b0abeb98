"""benchmarks/torch_parity.py: torch is given the runtime's cameras and images bit for bit, and
renders from them (not from its own head's)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from benchmarks import torch_parity as tp


def _runtime_like_scene(seed: int = 0) -> SimpleNamespace:
    """What ``IrisRuntime.encode(cameras="model")`` leaves: float32 outputs widened to float64."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4, dtype=np.float32), (8, 1, 1))
    poses[:, :3, 3] = rng.normal(0, 0.1, (8, 3)).astype(np.float32)
    return SimpleNamespace(reference_images=rng.random((8, 3, 64, 64), dtype=np.float32),
                           world_from_cam=poses.astype(np.float64),
                           focal=np.array([1.1547962, 1.1547754], np.float32).astype(np.float64))


def test_torch_inputs_are_the_runtime_values():
    scene = _runtime_like_scene()
    inputs = tp.torch_inputs(scene)
    assert inputs["world_from_cam"].dtype == inputs["focal"].dtype == np.float32
    assert np.array_equal(inputs["world_from_cam"].astype(np.float64), scene.world_from_cam)
    assert np.array_equal(inputs["focal"].astype(np.float64), scene.focal)
    assert np.array_equal(inputs["images"], scene.reference_images)
    # Cameras that are not float32 values (solved, refined) have no float32 copy: refused.
    scene.world_from_cam = scene.world_from_cam.copy()
    scene.world_from_cam[1, 0, 3] += 1e-12
    with pytest.raises(ValueError, match="world_from_cam"):
        tp.torch_inputs(scene)


def test_torch_renders_from_the_given_cameras():
    pytest.importorskip("torch")
    import torch

    from tests.conftest import random_model
    model = random_model("tiny-rgb", blend_angle=0.02)
    inputs = tp.torch_inputs(_runtime_like_scene(1))
    images = torch.from_numpy(inputs["images"])
    wfc, focal = torch.from_numpy(inputs["world_from_cam"]), torch.from_numpy(inputs["focal"])
    refs, targets = [0, 2, 3, 5, 7], [1, 4, 6]
    _, scene, rgb, poses = tp.torch_pass(model, images, wfc, focal, refs, targets, size=(4, 4))
    assert np.array_equal(scene.world_from_cam.numpy(), inputs["world_from_cam"])
    assert np.array_equal(scene.focal.numpy(), inputs["focal"])
    assert np.array_equal(poses.numpy(), inputs["world_from_cam"][targets])
    assert np.array_equal(scene.images.numpy(), inputs["images"])
    # Its own head's cameras are others, and render otherwise: the swap is what was rendered.
    _, own, own_rgb, _ = tp.torch_pass(model, images, wfc, focal, refs, targets, size=(4, 4),
                                       own=True)
    assert not np.array_equal(own.world_from_cam.numpy(), inputs["world_from_cam"])
    assert not np.array_equal(own_rgb.numpy(), rgb.numpy())
    assert np.array_equal(own.field_maps.numpy(), scene.field_maps.numpy())

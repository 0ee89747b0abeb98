"""scripts/pose_landscape.py: the camera path against scipy's slerp, and a smoke run on a random tiny
model (1 held-out scene, 2 alphas, 64 rays) whose JSON holds finite numbers."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from . import conftest

torch = pytest.importorskip("torch")


def load_script():
    return conftest.load_script("pose_landscape")


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_path_is_slerp_from_identity_and_linear_in_the_centre():
    transform = pytest.importorskip("scipy.spatial.transform")
    Rotation, Slerp = transform.Rotation, transform.Slerp
    pl = load_script()
    rng = np.random.default_rng(0)
    T = np.tile(np.eye(4), (6, 1, 1))
    rots = Rotation.random(6, random_state=1)
    T[:, :3, :3] = rots.as_matrix()
    T[1, :3, :3] = Rotation.from_rotvec([0, 0, math.pi - 1e-9]).as_matrix()     # near a half turn
    T[2, :3, :3] = Rotation.from_rotvec([1e-12, 0, 0]).as_matrix()              # near the identity
    T[:, :3, 3] = rng.standard_normal((6, 3))
    np.testing.assert_allclose(pl.interpolate_poses(T, 0.0), np.tile(np.eye(4), (6, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(pl.interpolate_poses(T, 1.0), T, atol=1e-9)
    for alpha in (0.25, 0.5, 0.8):
        got = pl.interpolate_poses(T, alpha)
        for k in range(6):
            key = Rotation.concatenate([Rotation.identity(), Rotation.from_matrix(T[k, :3, :3])])
            expected = Slerp([0.0, 1.0], key)([alpha]).as_matrix()[0]
            np.testing.assert_allclose(got[k, :3, :3], expected, atol=1e-9)
        np.testing.assert_allclose(got[:, :3, 3], alpha * T[:, :3, 3], atol=1e-15)


def test_smoke_run_on_a_random_tiny_model(tmp_path, capsys):
    pytest.importorskip("iris_train.ibr")
    try:
        from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
        SyntheticScenes([HELDOUT_SEEDS[0]])[0]
    except Exception as exc:                       # no cache and no EGL renderer here
        pytest.skip(f"held-out scene unavailable: {exc}")
    from iris_train import build_model, preset
    from iris_train.model import save_checkpoint
    torch.manual_seed(0)
    ckpt = tmp_path / "tiny.pt"
    save_checkpoint(ckpt, build_model(preset("tiny")))
    out = tmp_path / "landscape.json"
    pl = load_script()
    argv = [str(ckpt), "--scenes", "1", "--alphas", "0,1", "--rays", "64", "--threads", "1",
            "--json", str(out)]
    assert pl.main(argv) == 0
    printed = capsys.readouterr()
    assert "gain alpha 0 -> 1" in printed.out and "pred" in printed.out
    assert "scene 1" in printed.err                 # progress on stderr

    doc = json.loads(out.read_text())
    assert doc["alphas"] == [0.0, 1.0] and len(doc["rows"]) == 2 and len(doc["per_scene"]) == 1
    for row in doc["rows"] + [doc["predicted"]]:
        for name in ("learned", "plane_sweep"):
            assert np.isfinite(row[name]["psnr"]) and 0 < row[name]["psnr"] <= 100
            assert np.isfinite(row[name]["mse"]) and row[name]["mse"] >= 0
    assert np.isfinite(doc["gain"]["learned"]) and np.isfinite(doc["gain"]["plane_sweep"])

    # Deterministic: a second run gives the same numbers.
    out2 = tmp_path / "again.json"
    assert pl.main(argv[:-1] + [str(out2)]) == 0
    assert json.loads(out2.read_text())["rows"] == doc["rows"]

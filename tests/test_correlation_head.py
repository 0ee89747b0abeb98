"""The correlation camera head (``ModelConfig.camera_head = "correlation"``,
``iris_train.correlation``) and the config field that selects it. What is checked:

* the config: default "tokens", checkpoints without the field load as "tokens", an unknown head
  is an ``InputError`` naming the field; the token head computes bit for bit what it computed
  before the field existed (its old forward, inlined here as the reference), on a random model
  and on the shipped checkpoint;
* the parts against plain references: the correlation volume (a loop of cosine similarities),
  the spatial-softmax keypoints;
* the head: shapes, view 0 exactly the identity, rigid poses near the identity at
  initialisation, bounded focal; order-free over views 1..V-1; **reference isolation** (the
  references' cameras equal whether queries are present, changed or absent); every parameter of
  the head gets a gradient from a pose loss, and so does the encoder;
* the fine-tune rule of ``iris-train --init CKPT --camera-head correlation``
  (``train.load_init_weights``): every shared weight loads, only the new head's own parameters
  stay fresh, any other mismatch is an error; ``model_config``; a short ``train`` run from a
  token checkpoint; ``--camera-head`` choices; resuming with another head is refused;
* export (one dynamo export of the encoder graph per module; the renderer graphs are those of
  conftest's random tiny model, whose field and renderer weights the correlation model shares):
  the project's validation (probes within tolerance, isolation inside ONNX Runtime) passes, the
  graph holds standard ONNX ops only, ONNX Runtime matches torch on 8 views, and ``IrisRuntime``
  encodes with the exported directory.
"""
from __future__ import annotations

import copy
import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from iris_runtime.errors import InputError                                      # noqa: E402
from iris_train.camera_head import CameraHead                                   # noqa: E402
from iris_train.config import ModelConfig, preset                               # noqa: E402
from iris_train.correlation import (CorrelationCameraHead, correlation_volume,  # noqa: E402
                                    spatial_softmax_keypoints)
from iris_train.model import build_model, load_model                            # noqa: E402
from iris_train.train import (TrainConfig, load_init_weights, main as train_main,  # noqa: E402
                              model_config, train)

from .tolerances import correlation_head_terms, encoder_tol, f32_tol            # noqa: E402

pytestmark = pytest.mark.torch

ROOT = Path(__file__).resolve().parents[1]
CFG = dataclasses.replace(preset("tiny"), camera_head="correlation")
H, W = CFG.image_height, CFG.image_width
#: A small config for the loading-rule tests (fast to build).
SMALL_CFG = ModelConfig(image_height=32, image_width=32, encoder_width=32, encoder_heads=2,
                        encoder_pairs=1, field_width=16, field_heads=2, ray_blocks=1, samples=8)


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """The machine is shared: torch at 1 thread (2 busy cores make 2 threads much slower)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def spread(model):
    """The model with a pose layer 30x larger: cameras a few degrees apart, so that tests are not
    fooled by near-identical cameras (test_model's ``spread_model``)."""
    m = copy.deepcopy(model)
    with torch.no_grad():
        m.camera_head.fused_pose_mlp[-1].weight.mul_(30.0)
    return m


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return build_model(CFG).eval()


@pytest.fixture(scope="module")
def spread_model(model):
    return spread(model)


@pytest.fixture(scope="module")
def images():
    from export.validate import scene_images
    return scene_images(6, H, W, torch.Generator().manual_seed(1))


def rotation_angles_deg(world_from_cam: torch.Tensor) -> torch.Tensor:
    R = world_from_cam[..., :3, :3].double()
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    return torch.rad2deg(torch.arccos(cos))


# -- config and the token head --------------------------------------------------------------------
def test_camera_head_config_field():
    assert ModelConfig().camera_head == "tokens" and preset("tiny-rgb").camera_head == "tokens"
    old = preset("tiny-rgb").to_dict()
    del old["camera_head"]                             # a checkpoint written before the field
    assert ModelConfig.from_dict(old) == preset("tiny-rgb")
    assert ModelConfig.from_dict(CFG.to_dict()) == CFG
    for bad in ("Tokens", "cost-volume", "", None):
        with pytest.raises(InputError, match="camera_head"):
            ModelConfig(camera_head=bad)
        with pytest.raises(InputError, match="camera_head"):
            ModelConfig.from_dict({**ModelConfig().to_dict(), "camera_head": bad})
    with pytest.raises(InputError, match="patch_size"):
        ModelConfig(image_height=60, image_width=60, patch_size=4, camera_head="correlation")
    assert CFG.correlation_grid == (16, 16)
    assert dataclasses.replace(CFG, correlation_scale=4).correlation_grid == (32, 32)
    del old["correlation_scale"]                       # a checkpoint written before that field
    assert ModelConfig.from_dict(old).correlation_scale == 2
    for bad in (1, 3, 8, "4", None):
        with pytest.raises(InputError, match="correlation_scale"):
            ModelConfig(camera_head="correlation", correlation_scale=bad)
    assert isinstance(build_model(SMALL_CFG).camera_head, CameraHead)
    assert isinstance(build_model(dataclasses.replace(SMALL_CFG, camera_head="correlation")).camera_head,
                      CorrelationCameraHead)


def _old_token_head(head: CameraHead, camera_tokens: torch.Tensor):
    """``CameraHead.forward`` as it was before ``camera_head`` existed (verbatim)."""
    from iris_train.geometry import rotation_from_6d
    B, V, D = camera_tokens.shape
    token0 = camera_tokens[:, :1].expand(B, V, D)
    out = head.pose_mlp(torch.cat([camera_tokens, token0], dim=-1))
    R = rotation_from_6d(head.identity_6d + out[..., :6])
    t = out[..., 6:, None]
    bottom = torch.zeros_like(camera_tokens[..., :4])
    bottom = bottom + torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=bottom.dtype, device=bottom.device)
    pose = torch.cat([torch.cat([R, t], dim=-1), bottom[..., None, :]], dim=-2)
    is_canonical = (torch.arange(V, device=pose.device) == 0)[None, :, None, None]
    eye = torch.eye(4, dtype=pose.dtype, device=pose.device)
    world_from_cam = torch.where(is_canonical, eye, pose)
    focal = torch.exp(head.log_focal_min + head.log_focal_range
                      * torch.sigmoid(head.focal_mlp(camera_tokens[:, 0])))
    return world_from_cam, focal


# G1's weights with its token head: the training state the shipped model's renderer came from.
G1 = ROOT / "models" / "iris-tiny-rgb.train.pt"


@pytest.mark.parametrize("source", ["random", "g1"])
def test_token_head_is_bitwise_what_it_was(source, images):
    """Checkpoints without the field (all existing ones) build the token head, load strictly and
    give bit for bit the cameras of the token head's old forward."""
    if source == "g1":
        if not G1.is_file():
            pytest.skip("no G1 checkpoint")
        tokens_model = load_model(G1)
        assert "camera_head" not in torch.load(G1, map_location="cpu",
                                               weights_only=True)["config"]
    else:
        torch.manual_seed(0)
        tokens_model = build_model(preset("tiny")).eval()
        with torch.no_grad():
            tokens_model.camera_head.pose_mlp[-1].weight.mul_(30.0)
    assert tokens_model.cfg.camera_head == "tokens" and type(tokens_model.camera_head) is CameraHead
    with torch.no_grad():
        _, tokens = tokens_model.encoder(images[None], torch.arange(6) < 4)
        want = _old_token_head(tokens_model.camera_head, tokens)
        _, world_from_cam, focal = tokens_model.encode_batch(images[None], torch.arange(6) < 4)
    assert torch.equal(world_from_cam, want[0]) and torch.equal(focal, want[1])
    assert rotation_angles_deg(world_from_cam[0, 1:]).max() > 0.5      # not trivially the identity


def test_seeded_token_model_has_the_weights_it_had():
    """``build_model`` of a token-head config draws the same random weights as the old builder
    (the stages in the same order), so seeded test models and runs are unchanged."""
    from iris_train.encoder import MultiViewEncoder
    from iris_train.latent_field import LatentField
    from iris_train.model import IrisModel
    from iris_train.ray_renderer import RayRenderer
    cfg = preset("tiny-rgb")
    torch.manual_seed(0)
    old = IrisModel(cfg, MultiViewEncoder(cfg), CameraHead(cfg), LatentField(cfg), RayRenderer(cfg))
    torch.manual_seed(0)
    new = build_model(cfg)
    a, b = old.state_dict(), new.state_dict()
    assert list(a) == list(b) and all(torch.equal(a[k], b[k]) for k in a)


# -- the parts ----------------------------------------------------------------------------------------
def test_correlation_volume_against_a_loop():
    g = torch.Generator().manual_seed(0)
    B, V, C, h, w = 2, 3, 5, 3, 4
    f = torch.randn(B, V, C, h, w, generator=g, dtype=torch.float64)
    corr = correlation_volume(f)
    assert corr.shape == (B, V, h * w, h, w)
    want = torch.empty_like(corr)
    for b in range(B):
        for i in range(V):
            for y0 in range(h):
                for x0 in range(w):
                    a = f[b, 0, :, y0, x0]
                    for y in range(h):
                        for x in range(w):
                            c = f[b, i, :, y, x]
                            want[b, i, y0 * w + x0, y, x] = a @ c / (a.norm() * c.norm())
    torch.testing.assert_close(corr, want, rtol=0, atol=1e-12)
    # View 0 against itself: 1 on the "diagonal" (each position matches itself).
    diag = corr[:, 0].reshape(B, h * w, h * w).diagonal(dim1=1, dim2=2)
    torch.testing.assert_close(diag, torch.ones_like(diag), rtol=0, atol=1e-12)
    # Zero descriptors stay finite (the normalisation has a floor).
    assert torch.isfinite(correlation_volume(torch.zeros(1, 2, C, h, w))).all()


def test_spatial_softmax_keypoints():
    h, w = 4, 6
    x = torch.zeros(2, 3, h, w)
    torch.testing.assert_close(spatial_softmax_keypoints(x), torch.zeros(2, 3, 2))   # uniform
    x[0, 1, 2, 5] = 50.0                                    # one sharp peak: its cell centre
    kp = spatial_softmax_keypoints(x)
    # The peak's softmax weight rounds to 1 (the others are e^-50), so the keypoint is its cell
    # centre (arange + 0.5) * (2 / w) - 1 as float32 computes it (3 roundings of values <= 2)
    # against the float64 centre rounded once: at most 6 roundings of magnitude <= 1 (a strict
    # bound, tests/tolerances.py). A keypoint one cell off moves by 2 / w = 0.33.
    torch.testing.assert_close(kp[0, 1], torch.tensor([(5.5 / w) * 2 - 1, (2.5 / h) * 2 - 1]),
                               rtol=0, atol=f32_tol(6))
    assert kp.shape == (2, 3, 2) and torch.all(kp.abs() <= 1)


# -- the head -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("V", [1, 2, 5])
def test_shapes_identity_and_rigid_near_identity_at_init(model, images, V):
    with torch.no_grad():
        scene = model.encode(images[:V])
    assert scene.world_from_cam.shape == (V, 4, 4) and scene.focal.shape == (2,)
    assert torch.equal(scene.world_from_cam[0], torch.eye(4))
    R = scene.world_from_cam[:, :3, :3].double()
    torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(3, dtype=torch.float64).expand(V, 3, 3),
                               atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(V, dtype=torch.float64), atol=1e-5, rtol=0)
    assert torch.equal(scene.world_from_cam[:, 3], torch.tensor([0.0, 0, 0, 1]).expand(V, 4))
    # Cameras start near the identity (small last layer), the focal near 1.
    assert rotation_angles_deg(scene.world_from_cam).max() < 10.0
    assert scene.world_from_cam[:, :3, 3].norm(dim=-1).max() < 0.2
    assert torch.all((scene.focal > 0.9) & (scene.focal < 1.1))
    with pytest.raises(ValueError, match="images"):
        model.camera_head(torch.zeros(1, V, CFG.encoder_width), None)
    with pytest.raises(ValueError, match="images"):
        model.camera_head(torch.zeros(1, V, CFG.encoder_width), torch.zeros(1, V, 3, 32, 32))


def test_order_free_over_views(spread_model, images):
    perm = [0, 3, 1, 2]
    with torch.no_grad():
        scene = spread_model.encode(images[:4])
        scene_p = spread_model.encode(images[:4][perm])
    assert rotation_angles_deg(scene.world_from_cam[1:]).min() > 1.0
    torch.testing.assert_close(scene_p.world_from_cam, scene.world_from_cam[perm], atol=1e-5, rtol=0)
    torch.testing.assert_close(scene_p.focal, scene.focal, atol=1e-5, rtol=0)


def _with_queries(model, refs, queries):
    V = refs.shape[0]
    batch = torch.cat([refs, queries])
    _, world_from_cam, focal = model.encode_batch(batch[None], torch.arange(len(batch)) < V)
    return world_from_cam[0, :V], focal[0], world_from_cam[0, V:]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_reference_isolation(spread_model, images, dtype):
    """The references' cameras (and focal) are the same whether query views are present, changed
    or absent: the evidence of view i is its correlation with view 0, a reference. Present vs
    changed is exact (same shapes, and a masked key's attention weight is exactly 0). Present vs
    absent differs by rounding only: the attention rows have another length and every layer
    runs on another batch, which may take other kernels or another summation order (on another
    CPU or thread count). In float64 that comparison is held to 1e-10 absolute; in float32 to the
    rounding of the encoder and the head (``tests/tolerances.py``: ``encoder_tol``, ~5e-5 of the
    output scale here; measured 1.1e-6 on an AMD EPYC and 1.07e-6 on an Intel Xeon, where the
    former literal 1e-6 failed). Not isolating the queries (every view a reference) moves the
    references' cameras by 0.18 and the focal by 1.2e-4 (measured with this model), 3000x and
    4x their float32 tolerances; the float64 twin catches any leak."""
    model = copy.deepcopy(spread_model).to(dtype)
    images = images.to(dtype)
    refs, queries = images[:3], images[3:]
    other = torch.rand(queries.shape, generator=torch.Generator().manual_seed(9)).to(dtype)
    with torch.no_grad():
        alone = model.encode(refs)
        present = _with_queries(model, refs, queries)
        changed = _with_queries(model, refs, other)
        more = _with_queries(model, refs, torch.cat([queries, other]))
        # The evidence itself: each view against view 0, whatever else is in the batch.
        ev_all = model.camera_head.evidence(images[None])
        ev_refs = model.camera_head.evidence(refs[None])
    assert torch.equal(changed[0], present[0]) and torch.equal(changed[1], present[1])
    views = len(refs) + 2 * len(queries)                 # the longest batch: ``more``
    if dtype == torch.float32:
        tol = encoder_tol(CFG, views, "cameras", max(1.0, float(alone.world_from_cam.abs().max())))
        focal_tol = encoder_tol(CFG, views, "focal", max(1.0, float(alone.focal.max())))
        # The evidence: the head's stem and correlation network on 6 views vs 3 (another conv
        # batch); GroupNorm'd means and keypoints in [-1, 1]. Not a sum over views: a bug that
        # mixed views would move it by O(0.1).
        ev_tol = f32_tol(correlation_head_terms(CFG), max(1.0, float(ev_refs.abs().max())))
    else:
        tol = focal_tol = ev_tol = 1e-10
    for poses, focal, _ in (present, changed, more):
        assert (poses - alone.world_from_cam).abs().max() <= tol
        assert (focal - alone.focal).abs().max() <= focal_tol
    torch.testing.assert_close(ev_all[:, :3], ev_refs, rtol=0, atol=ev_tol)
    # The queries' own cameras come from their images (they do differ).
    assert (present[2] - changed[2]).abs().max() > 1e-3


def test_pose_loss_reaches_every_head_parameter_and_the_encoder(images):
    torch.manual_seed(0)
    model = build_model(CFG).train()
    _, world_from_cam, focal = model.encode_batch(images[None, :4])
    target = torch.eye(4).expand(3, 4, 4) + 0.1
    loss = ((world_from_cam[0, 1:] - target) ** 2).mean() + ((focal - 1.3) ** 2).mean()
    loss.backward()
    dead = [n for n, p in model.camera_head.named_parameters()
            if p.grad is None or not torch.any(p.grad != 0) or not torch.all(torch.isfinite(p.grad))]
    assert dead == []
    assert model.encoder.patch_embed.weight.grad is not None
    assert torch.any(model.encoder.patch_embed.weight.grad != 0)


# -- the fine-tune rule (iris-train --init CKPT --camera-head correlation) ----------------------------
def _payload(model, drop_head_field=True, **override):
    config = model.cfg.to_dict()
    if drop_head_field:
        del config["camera_head"]                           # as old token-head checkpoints
    return {"config": config, "model": model.state_dict(), **override}


def test_load_init_weights_keeps_only_the_new_head_fresh():
    torch.manual_seed(1)
    tokens_model = build_model(SMALL_CFG)
    torch.manual_seed(2)
    corr = build_model(dataclasses.replace(SMALL_CFG, camera_head="correlation"))
    before = {k: v.clone() for k, v in corr.state_dict().items()}
    fresh = load_init_weights(corr, _payload(tokens_model))
    head_keys = {k for k in before if k.startswith("camera_head.")}
    assert fresh and set(fresh) == {k for k in head_keys if not k.startswith("camera_head.focal_mlp.")}
    assert any(k.startswith("camera_head.stem.") for k in fresh)
    old = tokens_model.state_dict()
    for k, v in corr.state_dict().items():
        want = before[k] if k in fresh else old[k]   # the focal head loads: same name and shape
        assert torch.equal(v, want), k
    # The old head's pose MLP is dropped, not half-loaded into the new one.
    assert not any(k.startswith("camera_head.pose_mlp.") for k in corr.state_dict())

    # Same head: strict, nothing fresh (an old checkpoint without the field is a token head).
    other = build_model(SMALL_CFG)
    assert load_init_weights(other, _payload(tokens_model)) == []
    assert all(torch.equal(a, b) for a, b in zip(other.state_dict().values(), old.values()))


def test_finer_correlation_grid_shapes_and_init_from_the_coarser_head(images):
    """correlation_scale 4 correlates a grid twice as fine (32x32 at 64x64: the stem keeps the
    second conv's size) and still starts every camera near the identity; from a scale-2
    correlation checkpoint, only the head weights of another shape stay fresh."""
    fine_cfg = dataclasses.replace(CFG, correlation_scale=4)
    torch.manual_seed(0)
    fine = build_model(fine_cfg).eval()
    with torch.no_grad():
        d = fine.camera_head.stem(images)
        _, poses, focal = fine.encode_batch(images[None])
    assert d.shape == (6, 64, 32, 32)
    assert poses.shape == (1, 6, 4, 4) and torch.isfinite(poses).all() and focal.shape == (1, 2)
    assert rotation_angles_deg(poses[0, 1:]).max() < 5.0
    torch.manual_seed(1)
    coarse = build_model(CFG)
    before = {k: v.clone() for k, v in fine.state_dict().items()}
    fresh = load_init_weights(fine, _payload(coarse, drop_head_field=False))
    assert fresh == ["camera_head.correlation_net.0.weight"]    # 1024 positions in, not 256
    for k, v in fine.state_dict().items():
        assert torch.equal(v, before[k] if k in fresh else coarse.state_dict()[k]), k


@pytest.mark.parametrize("kind", ["missing_encoder_key", "unexpected_key", "other_shape",
                                  "other_config"])
def test_load_init_weights_refuses_other_mismatches(kind):
    torch.manual_seed(1)
    tokens_model = build_model(SMALL_CFG)
    corr = build_model(dataclasses.replace(SMALL_CFG, camera_head="correlation"))
    payload = _payload(tokens_model)
    state = dict(payload["model"])
    if kind == "missing_encoder_key":
        del state["encoder.norm.weight"]
    elif kind == "unexpected_key":
        state["renderer.extra"] = torch.zeros(3)
    elif kind == "other_shape":
        state["camera_head.focal_mlp.0.weight"] = torch.zeros(3, 3)
    else:
        payload["config"] = {**payload["config"], "field_width": 32}
    payload["model"] = state
    with pytest.raises(ValueError, match="init"):
        load_init_weights(corr, payload, "init")


def test_model_config_picks_the_head():
    assert model_config(TrainConfig()).camera_head == "tokens"
    assert model_config(TrainConfig(camera_head="correlation")).camera_head == "correlation"
    old = preset("tiny").to_dict()
    del old["camera_head"]
    assert model_config(TrainConfig(), old).camera_head == "tokens"
    assert model_config(TrainConfig(), {**old, "camera_head": "correlation"}) == CFG
    assert model_config(TrainConfig(camera_head="correlation"), old) == CFG
    with pytest.raises(ValueError, match="camera_head"):
        model_config(TrainConfig(camera_head="flow"))


def test_a_wider_depth_range_keeps_the_unit_and_every_weight():
    """``--far`` widens the sampled range only: the scene's median depth stays where the preset's
    rule puts it (the solve's ``depth_range`` is the preset's (near, far) exactly, as the teacher
    store's key has it), and a fine-tune from a model of the old range loads every weight."""
    base = preset("tiny")
    wide = model_config(TrainConfig(far=1.9))
    assert (wide.near, wide.far, wide.median_depth) == (base.near, 1.9, pytest.approx(0.55))
    assert wide.unit_range == (base.near, base.far)                # exactly: the store's key
    assert base.unit_range == (base.near, base.far) and base.median_depth == 0
    torch.manual_seed(1)
    source = build_model(SMALL_CFG)
    target = build_model(dataclasses.replace(SMALL_CFG, far=2.5, samples=32, median_depth=0.7))
    assert load_init_weights(target, _payload(source, drop_head_field=False)) == []
    assert all(torch.equal(a, b) for a, b in zip(target.state_dict().values(),
                                                 source.state_dict().values()))


def test_train_from_a_token_checkpoint_with_the_correlation_head(tmp_path, capsys):
    """iris-train --init TOKENS_CKPT --camera-head correlation: one step, the checkpoint is a
    correlation model whose encoder started from the token checkpoint's; resuming it with the
    token head is refused; --camera-head takes the two heads only."""
    from .test_train import SMALL, fake_scenes
    scenes = fake_scenes()
    train(TrainConfig(steps=1, **SMALL), tmp_path / "tokens", scenes=scenes, threads=1)
    init = tmp_path / "tokens" / "last.pt"
    train(TrainConfig(steps=1, camera_head="correlation", **SMALL), tmp_path / "corr",
          scenes=scenes, threads=1, init=init)
    assert "camera head start fresh" in capsys.readouterr().err
    model = load_model(tmp_path / "corr" / "last.pt")
    assert model.cfg == CFG and isinstance(model.camera_head, CorrelationCameraHead)
    log = [json.loads(x) for x in (tmp_path / "corr" / "log.jsonl").read_text().splitlines()]
    assert np.isfinite(log[0]["loss"])
    # Resuming the correlation run keeps its head by default, refuses another.
    train(TrainConfig(steps=2, **SMALL), tmp_path / "corr", scenes=scenes, threads=1, resume=True)
    assert load_model(tmp_path / "corr" / "last.pt").cfg.camera_head == "correlation"
    with pytest.raises(ValueError, match="camera head"):
        train(TrainConfig(steps=3, camera_head="tokens", **SMALL), tmp_path / "corr",
              scenes=scenes, threads=1, resume=True)
    with pytest.raises(SystemExit):
        train_main(["--out", str(tmp_path / "x"), "--camera-head", "flow"])
    assert "--camera-head" in capsys.readouterr().err


# -- export and runtime -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def exported(torch_export, tmp_path_factory):
    """(model_dir, correlation model): the session's random tiny model (conftest) with the
    correlation head added (``load_init_weights``: its encoder, field and renderer weights; the
    head fresh, its pose layer spread), exported by ``export_model`` (quick validation, one
    thread). Only the encoder graph is exported here; the renderer graphs are conftest's,
    which hold the same field and renderer weights (and are validated again against this model)."""
    from export import io_spec, pipeline
    from export.graphs import GraphFile, export_graph
    src_dir, tokens_model = torch_export
    torch.manual_seed(3)
    corr = build_model(dataclasses.replace(tokens_model.cfg, camera_head="correlation"))
    load_init_weights(corr, _payload(tokens_model, drop_head_field=False))
    corr = spread(corr).eval()

    def export_encoder_copy_renderers(model, graph, path, opset=io_spec.DEFAULT_OPSET, wrapper=None):
        if graph == "encoder":
            return export_graph(model, graph, path, opset, wrapper)
        src = Path(src_dir) / io_spec.spec_for(graph)["file"]
        shutil.copyfile(src, path)
        return GraphFile(graph, Path(path), 0, 0.0)

    out = tmp_path_factory.mktemp("corr_export") / "model"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pipeline, "export_graph", export_encoder_copy_renderers)
        pipeline.export_model(corr, out, quick=True, progress=False, threads=1)
    return out, corr


def test_export_validates_with_isolation(exported):
    from export.manifest import read_manifest
    out, corr = exported
    m = read_manifest(out)
    assert m["config"]["camera_head"] == "correlation"
    enc = m["validation"]["encoder"]
    assert enc["passed"] and enc["enforced"]
    assert all(0 <= e <= t for e, t in zip(enc["max_abs_error"].values(), enc["tolerance"].values()))
    assert {p["queries"] for p in enc["probes"]} >= {0, 1, 2, 3}
    assert enc["isolation"]["passed"]
    assert m["validation"]["renderer"]["passed"]


def test_encoder_graph_uses_standard_ops_only(exported):
    onnx = pytest.importorskip("onnx")
    proto = onnx.load(str(exported[0] / "encoder.onnx"))
    ops = {(n.domain, n.op_type) for n in proto.graph.node}
    assert {d for d, _ in ops} <= {"", "ai.onnx"}
    assert not {op for _, op in ops} & {"Inverse", "Svd", "SVD", "Det", "Einsum"}
    assert "Conv" in {op for _, op in ops}                   # the correlation head is in the graph


def test_onnxruntime_matches_torch_on_8_views(exported):
    ort = pytest.importorskip("onnxruntime")
    from export.io_spec import ENCODER
    from export.validate import scene_images
    out, corr = exported
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    sess = ort.InferenceSession(str(out / "encoder.onnx"), options, providers=["CPUExecutionProvider"])
    images = scene_images(8, H, W, torch.Generator().manual_seed(11))
    is_reference = torch.arange(8) < 6                       # two queries at the end
    maps, poses, focal = sess.run(None, {"images": images.numpy(), "is_reference": is_reference.numpy()})
    with torch.no_grad():
        features, want_poses, want_focal = corr.encode_batch(images[None], is_reference)
        want_maps = corr.field.prepare(features[0])
    assert rotation_angles_deg(want_poses[0, 1:]).min() > 1.0        # cameras really differ
    tol = ENCODER["tolerance"]
    np.testing.assert_allclose(poses, want_poses[0].numpy(), rtol=0, atol=tol["world_from_cam"])
    np.testing.assert_allclose(focal, want_focal[0].numpy(), rtol=0, atol=tol["focal"])
    np.testing.assert_allclose(maps, want_maps.numpy(), rtol=0, atol=tol["field_maps"])


def test_runtime_encodes_with_the_correlation_model(exported):
    from iris_runtime import IrisRuntime
    out, corr = exported
    from export.validate import scene_images
    images = scene_images(4, H, W, torch.Generator().manual_seed(12))
    photos = [np.round(im.permute(1, 2, 0).numpy() * 255).astype(np.uint8) for im in images]
    rt = IrisRuntime(out, threads=1)
    scene = rt.encode(photos, cameras="model")
    with torch.no_grad():
        want = corr.encode(torch.from_numpy(np.stack(photos)).permute(0, 3, 1, 2).float() / 255.0)
    np.testing.assert_allclose(scene.world_from_cam, want.world_from_cam.numpy(), rtol=0, atol=1e-5)
    np.testing.assert_allclose(scene.focal, want.focal.numpy(), rtol=0, atol=1e-5)
    assert np.array_equal(scene.world_from_cam[0], np.eye(4))

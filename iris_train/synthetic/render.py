"""The pyrender backend (OpenGL through EGL): ``render_spec`` and the size reduction of a scene.

See the package docstring for the supersampling and the depth read at pixel centres. Capture
kinds (``SceneSpec.depth_target`` set) are first probed: their depth is rendered at a fixed small
size (``PROBE_HEIGHT`` rows, from the normalised intrinsics, so the probe does not depend on the
output size), and world and cameras are scaled so that the median valid depth is the target,
kept within ``DEPTH_BOUNDS`` at the 1st / 99th percentiles. A uniform scale of world and cameras
leaves the images unchanged and multiplies depth: so the views are rendered once in the scene's
own units and only the camera centres, the depth, and the markers are scaled.
"""
from __future__ import annotations

import contextlib
import functools
import os

import cv2
import numpy as np

from iris_runtime.errors import InputError

from .paths import intrinsics_off_centre
from .scene import (GL_FROM_CV, MARKER_COLORS, MARKER_RADIUS, MARKER_SUBDIVISIONS, SUPERSAMPLE,
                    ZFAR, ZNEAR, SceneData, SceneSpec)

#: Rows of the depth probe of the capture kinds (width follows the aspect ratio).
PROBE_HEIGHT = 48
#: Where the 1st and 99th percentiles of a capture scene's valid depth must lie after scaling.
DEPTH_BOUNDS = (0.12, 1.2)


@contextlib.contextmanager
def _single_sample_framebuffers():
    """Make pyrender allocate its 'multisample' framebuffer with 0 samples (plain buffers).

    pyrender hard-codes 4x MSAA and resolves depth from one off-centre sample; we supersample
    ourselves instead and read depth at pixel centres. The patch is scoped to our render calls.
    """
    import pyrender.renderer as prr

    original = prr.glRenderbufferStorageMultisample

    def storage(target, samples, fmt, width, height):
        return original(target, 0, fmt, width, height)

    prr.glRenderbufferStorageMultisample = storage
    try:
        yield
    finally:
        prr.glRenderbufferStorageMultisample = original


@functools.lru_cache(maxsize=1)
def _offscreen():
    """The process's one offscreen renderer (an EGL context), created on first use. One context
    whose framebuffer is resized per size: several contexts would be torn down together when
    one of them is garbage-collected (pyrender terminates the shared EGL display)."""
    try:
        import pyrender
        return pyrender.OffscreenRenderer(64, 64)
    except Exception as e:  # EGL missing/broken: say what to do
        raise RuntimeError(
            f"cannot create a pyrender offscreen renderer with PYOPENGL_PLATFORM="
            f"{os.environ.get('PYOPENGL_PLATFORM')!r} ({type(e).__name__}: {e}). Install Mesa's "
            f"EGL (libegl1) or set PYOPENGL_PLATFORM=osmesa before importing iris_train.synthetic."
        ) from e


def _renderer(width: int, height: int):
    """The offscreen renderer, set to render ``width`` x ``height`` pixels."""
    r = _offscreen()
    r.viewport_width, r.viewport_height = width, height
    return r


def _pyrender_scene(spec: SceneSpec):
    import pyrender
    from pyrender.constants import GLTF

    scene = pyrender.Scene(bg_color=np.array([*spec.background, 1.0]), ambient_light=np.array(spec.ambient))
    sampler = pyrender.Sampler(magFilter=GLTF.LINEAR, minFilter=GLTF.LINEAR_MIPMAP_LINEAR,
                               wrapS=GLTF.REPEAT, wrapT=GLTF.REPEAT)
    marker_nodes = {}
    for m in spec.meshes:
        if m.emissive is not None:
            # Black metal reflects (almost) nothing: no diffuse, specular f0 = base colour = 0,
            # only Schlick's Fresnel term at grazing angles adds a few levels of 255.
            mat = pyrender.MetallicRoughnessMaterial(baseColorFactor=[0.0, 0.0, 0.0, 1.0],
                                                     metallicFactor=1.0, roughnessFactor=1.0,
                                                     emissiveFactor=list(m.emissive))
        else:
            tex = None
            if m.texture is not None:
                tex = pyrender.Texture(source=m.texture, source_channels="RGB", sampler=sampler)
            mat = pyrender.MetallicRoughnessMaterial(baseColorFactor=[*m.color, 1.0],
                                                     baseColorTexture=tex, metallicFactor=0.0,
                                                     roughnessFactor=float(m.roughness))
        prim = pyrender.Primitive(positions=m.positions, normals=m.normals, texcoord_0=m.uvs,
                                  indices=m.faces, material=mat, mode=GLTF.TRIANGLES)
        node = scene.add(pyrender.Mesh([prim], name=m.name))
        if m.marker_index >= 0:
            marker_nodes[m.marker_index] = node
    for light in spec.lights:
        pose = np.eye(4)
        if light.kind == "directional":
            # pyrender lights shine along their node's -z axis.
            z = -np.asarray(light.direction, dtype=np.float64)
            z /= np.linalg.norm(z)
            x = np.cross([0.0, 0.0, 1.0] if abs(z[2]) < 0.99 else [1.0, 0.0, 0.0], z)
            x /= np.linalg.norm(x)
            pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, np.cross(z, x), z
            scene.add(pyrender.DirectionalLight(color=np.array(light.color), intensity=light.intensity),
                      pose=pose)
        else:
            pose[:3, 3] = light.position
            scene.add(pyrender.PointLight(color=np.array(light.color), intensity=light.intensity),
                      pose=pose)
    return scene, marker_nodes


def _probe_scale(spec: SceneSpec, scene, cam_node, renderer) -> tuple[float, dict]:
    """The factor that brings ``spec``'s median valid depth to ``spec.depth_target`` (see the
    module docstring) and the probe's depth statistics before scaling."""
    import pyrender

    h, w = spec.size
    ph, pw = PROBE_HEIGHT, max(1, round(PROBE_HEIGHT * w / h))
    K = intrinsics_off_centre((ph, pw), np.radians(spec.meta["yfov_deg"]),
                              np.asarray(spec.meta["principal_offset"]))
    probe = pyrender.IntrinsicsCamera(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2],
                                      znear=ZNEAR, zfar=ZFAR)
    node = scene.add(probe, pose=np.eye(4))
    scene.main_camera_node = node
    size = (renderer.viewport_width, renderer.viewport_height)
    renderer.viewport_width, renderer.viewport_height = pw, ph
    depths = []
    try:
        for T in spec.world_from_cam:
            scene.set_pose(node, T @ GL_FROM_CV)
            depths.append(renderer.render(scene, flags=pyrender.RenderFlags.DEPTH_ONLY))
    finally:
        renderer.viewport_width, renderer.viewport_height = size
        scene.main_camera_node = cam_node
        scene.remove_node(node)
    z = np.concatenate([d[d > 0] for d in depths]).astype(np.float64)
    if z.size == 0:
        raise RuntimeError(f"scene {spec.seed} ({spec.kind}): the cameras see no geometry")
    med, lo, hi = np.median(z), np.percentile(z, 1), np.percentile(z, 99)
    s = spec.depth_target / med
    s = max(min(s, DEPTH_BOUNDS[1] / hi), DEPTH_BOUNDS[0] / lo)   # the near bound wins
    return float(s), {"probe_median": float(med), "probe_p1": float(lo), "probe_p99": float(hi)}


def render_spec(spec: SceneSpec, supersample: int = SUPERSAMPLE) -> SceneData:
    """Render every camera of ``spec`` with pyrender (EGL); see the package docstring for AA/depth
    and the module docstring for the depth scaling of the capture kinds."""
    import pyrender

    if supersample < 1 or supersample % 2 == 0:
        raise InputError(f"supersample: expected an odd positive int, got {supersample}")
    h, w = spec.size
    s = supersample
    scene, marker_nodes = _pyrender_scene(spec)
    K = spec.K
    cam = pyrender.IntrinsicsCamera(fx=K[0, 0] * s, fy=K[1, 1] * s, cx=K[0, 2] * s, cy=K[1, 2] * s,
                                    znear=ZNEAR, zfar=ZFAR)
    cam_node = scene.add(cam, pose=np.eye(4))
    renderer = _renderer(w * s, h * s)
    scale, probe_info = 1.0, {}
    if spec.depth_target is not None:
        with _single_sample_framebuffers():
            scale, probe_info = _probe_scale(spec, scene, cam_node, renderer)
    V = spec.world_from_cam.shape[0]
    images = np.empty((V, h, w, 3), np.uint8)
    depth = np.empty((V, h, w), np.float32)
    coverage = np.zeros((V, len(marker_nodes), h, w), np.float32) if marker_nodes else None
    seg_colours = {node: np.array(MARKER_COLORS[i % len(MARKER_COLORS)], np.uint8)
                   for i, node in marker_nodes.items()}
    with _single_sample_framebuffers():
        for v in range(V):
            scene.set_pose(cam_node, spec.world_from_cam[v] @ GL_FROM_CV)
            colour, z = renderer.render(scene)
            # Area average of s x s sub-pixels = box-filtered anti-aliasing (in sRGB values).
            images[v] = cv2.resize(colour, (w, h), interpolation=cv2.INTER_AREA) if s > 1 else colour
            depth[v] = z[s // 2::s, s // 2::s]             # the sub-pixel at each pixel centre
            if coverage is not None:
                # One segmentation pass per marker, drawn alone: markers never hide each other.
                for i, node in marker_nodes.items():
                    seg, _ = renderer.render(scene, flags=pyrender.RenderFlags.SEG,
                                             seg_node_map={node: seg_colours[node]})
                    hit = np.all(seg == seg_colours[node], axis=-1).astype(np.float32)
                    coverage[v, i] = hit.reshape(h, s, w, s).mean(axis=(1, 3))
    meta = dict(spec.meta)
    meta["supersample"] = s
    world_from_cam = spec.world_from_cam.astype(np.float64)
    markers_world = spec.markers_world
    if spec.depth_target is not None:
        world_from_cam = world_from_cam.copy()
        world_from_cam[:, :3, 3] *= scale
        depth *= np.float32(scale)
        markers_world = markers_world * scale
        meta.update(scale=scale, **probe_info)
        if spec.anchors_world is not None:
            meta["anchors_world"] = (spec.anchors_world * scale).tolist()
    if spec.markers_world.shape[0]:
        meta["markers"] = {"centers_world": markers_world.tolist(), "radius": MARKER_RADIUS * scale,
                           "colors": [list(MARKER_COLORS[i % len(MARKER_COLORS)])
                                      for i in range(spec.markers_world.shape[0])],
                           "subdivisions": MARKER_SUBDIVISIONS}
        meta["marker_coverage"] = coverage
    return SceneData(images=images, world_from_cam=world_from_cam,
                     K=spec.K.astype(np.float64), depth=depth, meta=meta)


def downsample_scene(scene: SceneData, factor: int) -> SceneData:
    """``scene`` at 1/``factor`` of its size: images by area averaging (``cv2.INTER_AREA``),
    ``K`` scaled by 1/``factor`` (pixel centres at +0.5, so the scaling is exact), depth as the
    harmonic mean of each block's depths where the whole block sees geometry (exact on planes,
    where 1/z is affine in the pixel position; a blend across depth edges) and 0 elsewhere.
    The result equals a direct render at the smaller size up to anti-aliasing."""
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
        raise InputError(f"factor: expected a positive int, got {factor!r}")
    V, H, W = scene.images.shape[:3]
    if H % factor or W % factor:
        raise InputError(f"factor: {factor} does not divide the scene's size {H}x{W}")
    if factor == 1:
        return scene
    h, w = H // factor, W // factor
    images = np.stack([cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA) for im in scene.images])
    blocks = scene.depth.reshape(V, h, factor, w, factor).astype(np.float32, copy=False)
    valid = blocks > 0
    full = valid.all(axis=(2, 4))
    inv = np.reciprocal(blocks, where=valid, out=np.zeros_like(blocks)).mean(axis=(2, 4))
    depth = np.divide(1.0, inv, where=full, out=np.zeros((V, h, w), np.float32))
    K = np.diag([1.0 / factor, 1.0 / factor, 1.0]) @ scene.K
    meta = {k: v for k, v in scene.meta.items() if k != "marker_coverage"}
    meta["downsampled_from"] = [H, W]
    return SceneData(images=images, world_from_cam=scene.world_from_cam.copy(), K=K, depth=depth,
                     meta=meta)

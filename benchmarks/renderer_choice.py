"""Which renderer for the synthetic training data: pyrender (EGL) or Mitsuba 3 (scalar_rgb)?

Renders the same scene descriptions (``iris_train.synthetic.build_scene_spec``) with both and
reports, per 64x64 view: time, whether z-depth comes out, and Monte-Carlo noise of Mitsuba against
a high-sample reference (pyrender's rasterisation is noise-free, so "comparable quality" means a
Mitsuba image whose noise is small). Mitsuba renders direct lighting only (path, max_depth=2), the
same light transport as pyrender's rasterisation, so the comparison is about cost, not looks.

    python benchmarks/renderer_choice.py            # ~1-2 minutes on 2 cores
    python benchmarks/renderer_choice.py --json benchmarks/results/renderer_choice.json

Results and the decision are written up in docs/DATA.md.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from iris_train import synthetic as S  # noqa: E402

SEEDS = (0, 1, 2, 3, 4, 5)
SIZE = (64, 64)
N_VIEWS = 8


def bench_pyrender(specs, supersample: int) -> dict:
    S.render_spec(specs[0], supersample=supersample)          # context creation + shader compile
    t0 = time.perf_counter()
    for spec in specs:
        S.render_spec(spec, supersample=supersample)
    dt = time.perf_counter() - t0
    n = len(specs) * N_VIEWS
    return {"renderer": f"pyrender EGL, {supersample}x{supersample} supersampling",
            "ms_per_view": 1e3 * dt / n, "ms_per_scene": 1e3 * dt / len(specs), "depth": "z-depth"}


def _write_obj(path: Path, m: S.MeshSpec) -> None:
    lines = [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in m.positions]
    lines += [f"vt {u:.7f} {v:.7f}" for u, v in m.uvs]
    lines += [f"vn {x:.7f} {y:.7f} {z:.7f}" for x, y, z in m.normals]
    lines += ["f " + " ".join(f"{i + 1}/{i + 1}/{i + 1}" for i in f) for f in m.faces]
    path.write_text("\n".join(lines) + "\n")


def mitsuba_scene(spec: S.SceneSpec, view: int, spp: int, tmp: Path, depth: bool):
    import mitsuba as mi
    from PIL import Image

    h, w = spec.size
    yfov = float(np.degrees(2 * np.arctan(h / 2 / spec.K[1, 1])))
    # Mitsuba cameras: x left, y up, z forward -> flip x and y of the OpenCV camera.
    to_world = spec.world_from_cam[view] @ np.diag([-1.0, -1.0, 1.0, 1.0])
    d = {"type": "scene",
         "sensor": {"type": "perspective", "fov": yfov, "fov_axis": "y", "near_clip": 0.02,
                    "to_world": mi.ScalarTransform4f(to_world.tolist()),
                    "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"}},
                    "sampler": {"type": "independent", "sample_count": spp}},
         "ambient": {"type": "constant", "radiance": {"type": "rgb", "value": list(spec.ambient)}}}
    path_integrator = {"type": "path", "max_depth": 2}
    d["integrator"] = ({"type": "aov", "aovs": "dd.y:depth", "img": path_integrator} if depth
                       else path_integrator)
    for k, m in enumerate(spec.meshes):
        obj = tmp / f"m{k}.obj"
        if not obj.exists():
            _write_obj(obj, m)
            if m.texture is not None:
                Image.fromarray(m.texture).save(tmp / f"t{k}.png")
        if m.emissive is not None:
            bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}}
        elif m.texture is not None:
            bsdf = {"type": "diffuse", "reflectance": {"type": "bitmap", "filename": str(tmp / f"t{k}.png")}}
        else:
            bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(m.color)}}
        d[f"mesh{k}"] = {"type": "obj", "filename": str(obj), "bsdf": bsdf, "face_normals": False}
    for k, L in enumerate(spec.lights):
        rgb = {"type": "rgb", "value": [c * L.intensity for c in L.color]}
        if L.kind == "directional":
            d[f"light{k}"] = {"type": "directional", "direction": list(map(float, L.direction)),
                              "irradiance": rgb}
        else:
            d[f"light{k}"] = {"type": "point", "position": list(map(float, L.position)), "intensity": rgb}
    return mi.load_dict(d)


def bench_mitsuba(specs, spp_list=(4, 16, 64), ref_spp=512, views=2) -> list[dict]:
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    rows = []
    refs = {}
    with tempfile.TemporaryDirectory() as td:
        for si, spec in enumerate(specs[:3]):
            tmp = Path(td) / f"s{si}"
            tmp.mkdir()
            for v in range(views):
                scene = mitsuba_scene(spec, v, ref_spp, tmp, depth=False)
                refs[si, v] = np.clip(np.array(mi.render(scene)), 0, 1)
        for spp in spp_list:
            load_t = render_t = 0.0
            errs = []
            n = 0
            for si, spec in enumerate(specs[:3]):
                tmp = Path(td) / f"s{si}"
                for v in range(views):
                    t0 = time.perf_counter()
                    scene = mitsuba_scene(spec, v, spp, tmp, depth=True)
                    t1 = time.perf_counter()
                    img = np.array(mi.render(scene))
                    t2 = time.perf_counter()
                    load_t += t1 - t0
                    render_t += t2 - t1
                    n += 1
                    rgb = np.clip(img[..., :3], 0, 1)
                    mse = float(np.mean((rgb - refs[si, v]) ** 2))
                    errs.append(10 * np.log10(1.0 / max(mse, 1e-12)))
            rows.append({"renderer": f"mitsuba scalar_rgb, path max_depth=2, {spp} spp",
                         "ms_per_view": 1e3 * render_t / n, "ms_scene_load": 1e3 * load_t / n,
                         "noise_psnr_db_vs_512spp": float(np.mean(errs)),
                         "depth": "aov integrator (dd.y:depth)"})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args()
    specs = [S.build_scene_spec(s, N_VIEWS, SIZE) for s in SEEDS]
    rows = [bench_pyrender(specs, 1), bench_pyrender(specs, 3), bench_pyrender(specs, 5)]
    rows += bench_mitsuba(specs)
    for r in rows:
        print(json.dumps({k: (round(v, 2) if isinstance(v, float) else v) for k, v in r.items()}))
    if args.json:
        out = {"machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}",
               "size": SIZE, "seeds": SEEDS, "rows": rows}
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()

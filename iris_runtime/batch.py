"""``iris-batch MODEL_DIR SCENES_DIR -o OUT --orbit N [--ray ADDRESS|local]``: the orbit of every
scene folder, serially or on a Ray cluster (optional extra ``[batch]``: ray, tqdm).

Every folder of ``SCENES_DIR`` that holds photos is a scene (its photos in file-name order; a
folder without any is a failing scene); ``OUT/<folder>`` gets exactly what ``iris-render MODEL_DIR
photos... -o OUT/<folder> --orbit N`` writes — the orbit's PNGs (and depth), ``orbit.mp4``,
``orbit_poses.json``, the inputs' cameras (``transforms.json``, ``colmap/``, ``cameras.png``) —
because each scene *is* an ``iris-render`` run (``iris_runtime.render_job.render_scene``, the
function ``iris-render`` calls after parsing its arguments) on a runtime loaded once per worker.

- Serial (no ``--ray``): one ``IrisRuntime`` in this process renders the scenes in order.
- ``--ray local`` starts a Ray cluster on this machine, ``--ray ADDRESS`` joins one: ``--actors``
  Ray actors (default: the cluster's CPUs // ``--threads``) each hold one ``IrisRuntime`` (one model
  load per actor, not per scene) and take the next scene when they finish one; Ray places them.
  The driver reads the photos and writes the outputs, actors send bytes both ways, so nodes share
  no file system (MODEL_DIR must exist at the same path on every node).
- ``OUT/batch.json`` records each scene's outcome, time and worker (process id: with Ray, one
  per actor, so scenes sharing a worker shared one model load).
- A scene is rendered into a temporary folder and its files written to ``OUT/.<folder>.partial-*``,
  renamed to ``OUT/<folder>`` only when complete: a failing scene is reported with its error and
  leaves nothing under its name, and the other scenes go on; an actor that dies fails its scene
  only.
- Outputs are byte-identical between the serial and the Ray run with the same ``--threads``: the
  same code renders each scene, deterministically (tests/test_batch.py checks it).

Exit code 0 when every scene rendered, 1 when some failed (each named on stderr), 2 when nothing
could start (bad arguments, unreadable model, existing outputs without ``--force``).
"""
from __future__ import annotations

import argparse
import os
import secrets
import shutil
import sys
import tempfile
import time
from collections import deque
from pathlib import Path

from . import cli
from .errors import InputError, IrisError
from .fileio import atomic_write_json
from .manifest import CAMERAS, camera_name
from .quality import QUALITY_PRESETS
from .render_job import RenderOptions, render_scene

__all__ = ["SceneRenderer", "find_scenes", "render_options", "write_scene", "main"]

PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp", ".bmp", ".tif", ".tiff")


def find_scenes(scenes_dir: Path) -> list[Path]:
    """The scene folders of ``scenes_dir`` (non-hidden subfolders), sorted by name."""
    if not scenes_dir.is_dir():
        raise InputError(f"SCENES_DIR {scenes_dir}: not a directory")
    scenes = sorted(p for p in scenes_dir.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not scenes:
        raise InputError(f"SCENES_DIR {scenes_dir}: no scene folders in it")
    return scenes


def read_photos(scene: Path) -> dict[str, bytes]:
    """A scene's photos by file name, in name order (what an actor is sent)."""
    return {p.name: p.read_bytes() for p in sorted(scene.iterdir())
            if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES}


def render_options(args: argparse.Namespace) -> RenderOptions:
    """The render options of every scene, from iris-batch's parsed ``args``: its orbit, quietly
    (what ``iris-render ... --orbit N -q`` with the same options renders)."""
    return RenderOptions(orbit=args.orbit, fps=args.fps, precision=args.precision, quiet=True,
                         quality=args.quality, size=args.size, cameras=args.cameras,
                         depth=not args.no_depth)


class SceneRenderer:
    """One ``IrisRuntime`` (one model load) that renders whole scenes: the body of a Ray actor,
    and of the serial run."""

    def __init__(self, model_dir: str, threads: int, precision: str, providers=None):
        from .runtime import IrisRuntime
        self.rt = IrisRuntime(model_dir, threads=threads, precision=precision, providers=providers)

    def render(self, name: str, photos: dict[str, bytes], options: RenderOptions) -> dict:
        """``render_scene`` of scene ``name`` (its photos: file name -> bytes, rendered in this
        order) with ``options`` -> ``{"scene", "error", "files": {relative path: bytes},
        "worker", "seconds"}``; every failure is returned, never raised."""
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="iris-batch-") as tmp:
            src, out = Path(tmp) / "photos", Path(tmp) / "out"
            src.mkdir()
            try:
                if not photos:
                    raise InputError(f"no photos ({', '.join(PHOTO_SUFFIXES)}) in the folder")
                paths = []
                for file_name, data in photos.items():
                    (src / file_name).write_bytes(data)
                    paths.append(str(src / file_name))
                render_scene(self.rt, paths, out, options)
                files = {p.relative_to(out).as_posix(): p.read_bytes()
                         for p in sorted(out.rglob("*")) if p.is_file()}
                return {"scene": name, "error": None, "files": files, "worker": os.getpid(),
                        "seconds": time.perf_counter() - t0}
            except Exception as exc:             # a scene's failure is its report, not a crash
                kind = type(exc).__name__ if isinstance(exc, (IrisError, OSError)) else \
                    f"{type(exc).__name__} (unexpected)"
                message = (str(exc).splitlines() or [""])[0].replace(f"{src}{os.sep}", f"{name}/")
                return {"scene": name, "error": f"{kind}: {message}", "files": {},
                        "worker": os.getpid(), "seconds": time.perf_counter() - t0}


def write_scene(out_root: Path, name: str, files: dict[str, bytes], force: bool) -> None:
    """``files`` into ``out_root/name``, which appears only complete (written to a hidden partial
    folder, then renamed; with ``force`` an existing folder is replaced after that)."""
    partial = out_root / f".{name}.partial-{secrets.token_hex(6)}"
    partial.mkdir()                       # not mkdtemp: the folder gets the umask's permissions
    try:
        for rel, data in files.items():
            path = partial / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        final = out_root / name
        old = None
        if final.exists() and force:
            old = out_root / f".{name}.old-{secrets.token_hex(6)}"
            os.replace(final, old)
        os.replace(partial, final)
        if old is not None:
            shutil.rmtree(old)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise


def _serial(args, scenes: list[Path]):
    renderer = SceneRenderer(args.model_dir, args.threads, args.precision, args.providers)
    options = render_options(args)
    for scene in scenes:
        yield renderer.render(scene.name, read_photos(scene), options)


def _on_ray(args, scenes: list[Path]):
    """Scenes to actors: each idle actor gets the next scene; Ray places and runs the actors."""
    import ray
    from ray.exceptions import RayActorError

    if args.ray == "local":
        ray.init(num_cpus=len(os.sched_getaffinity(0)), include_dashboard=False,
                 logging_level="ERROR", log_to_driver=False)
    else:
        ray.init(address=args.ray, logging_level="ERROR", log_to_driver=False)
    try:
        cpus = int(ray.cluster_resources().get("CPU", 1))
        count = args.actors or max(1, min(len(scenes), cpus // args.threads))
        actor_class = ray.remote(num_cpus=args.threads)(SceneRenderer)
        idle = [actor_class.remote(args.model_dir, args.threads, args.precision, args.providers)
                for _ in range(count)]
        options = render_options(args)
        queue, pending = deque(scenes), {}
        while queue or pending:
            while idle and queue:
                scene, actor = queue.popleft(), idle.pop()
                ref = actor.render.remote(scene.name, read_photos(scene), options)
                pending[ref] = (scene, actor)
            if not pending:                     # every actor died: the rest cannot be rendered
                for scene in queue:
                    yield {"scene": scene.name, "error": "not rendered: every Ray actor died",
                           "files": {}, "seconds": 0.0}
                return
            (ref,), _ = ray.wait(list(pending), num_returns=1)
            scene, actor = pending.pop(ref)
            try:
                result = ray.get(ref)
                idle.append(actor)
            except RayActorError as exc:        # the actor is gone (crash, OOM, node lost)
                result = {"scene": scene.name, "files": {}, "seconds": 0.0,
                          "error": f"RayActorError: {(str(exc).splitlines() or [''])[0]}"}
            yield result
    finally:
        ray.shutdown()


def build_parser() -> argparse.ArgumentParser:
    p = cli._Parser(
        prog="iris-batch",
        description="Render the orbit of every scene folder in SCENES_DIR (what iris-render "
                    "--orbit N writes, into OUT/<folder>), serially or on Ray actors that each "
                    "hold one model. See docs/SERVING.md.")
    p.add_argument("model_dir", metavar="MODEL_DIR", help="directory written by iris-export")
    p.add_argument("scenes_dir", metavar="SCENES_DIR", help="one folder of photos per scene")
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output directory")
    p.add_argument("--orbit", metavar="N", type=cli._positive, required=True,
                   help="frames of each scene's orbit")
    p.add_argument("--ray", metavar="ADDRESS|local",
                   help="render on Ray: 'local' starts a cluster on this machine, else the "
                        "address of one (e.g. ray://head:10001 or auto); default: serially")
    p.add_argument("--actors", type=cli._positive, default=None,
                   help="Ray actors, each holding one model (default: cluster CPUs // threads)")
    p.add_argument("--threads", type=cli._positive, default=1,
                   help="ONNX Runtime threads per actor (and of the serial run; default 1)")
    p.add_argument("--size", metavar="HxW", type=cli._size, help="output size (default: the "
                   "model's)")
    p.add_argument("--fps", type=cli._positive, default=24, help="orbit.mp4 frame rate")
    p.add_argument("--quality", choices=list(QUALITY_PRESETS), default=None,
                   help="speed/error preset (default: the model's, as iris-render)")
    p.add_argument("--cameras", type=camera_name, choices=list(CAMERAS), default=None,
                   help="cameras of the inputs (default: the model's manifest)")
    p.add_argument("--precision", choices=["float32", "int8"], default="float32")
    p.add_argument("--providers", type=cli.providers_arg, default=None, metavar="A,B",
                   help="ONNX Runtime execution providers in priority order (default: the CPU)")
    p.add_argument("--no-depth", action="store_true", help="skip the depth PNG/NPY files")
    p.add_argument("--force", action="store_true", help="replace existing OUT/<folder> outputs")
    p.add_argument("-q", "--quiet", action="store_true", help="print nothing but failures")
    return p


def _progress(total: int, quiet: bool):
    try:
        from tqdm import tqdm
    except ImportError:                          # tqdm comes with [batch]; without it: no bar
        return None
    return tqdm(total=total, unit="scene", desc="iris-batch", disable=True if quiet else None)


def run(args: argparse.Namespace) -> int:
    from .runtime import IrisRuntime
    scenes = find_scenes(Path(args.scenes_dir))
    IrisRuntime(args.model_dir, precision=args.precision, providers=args.providers)  # checked
    out = Path(args.out)
    taken = [s.name for s in scenes if (out / s.name).exists()]
    if taken and not args.force:
        raise InputError(f"-o {out}: outputs of {len(taken)} scene(s) exist ({', '.join(taken[:3])}"
                         f"{', ...' if len(taken) > 3 else ''}); use --force to replace them")
    if args.ray:
        try:
            import ray  # noqa: F401
        except ImportError:
            raise InputError("--ray: ray is not installed; pip install 'iris-nvs[batch]'") \
                from None
    out.mkdir(parents=True, exist_ok=True)
    bar = _progress(len(scenes), args.quiet)
    say = (bar.write if bar is not None else print) if not args.quiet else (lambda *a: None)
    report, failed, t0 = [], [], time.perf_counter()
    try:
        for result in (_on_ray if args.ray else _serial)(args, scenes):
            name, error = result["scene"], result["error"]
            if error is None:
                try:
                    write_scene(out, name, result["files"], args.force)
                except OSError as exc:
                    error = f"{type(exc).__name__}: writing the outputs failed: {exc}"
            report.append({"scene": name, "ok": error is None, "error": error,
                           "seconds": round(result["seconds"], 3), "worker": result.get("worker"),
                           "files": len(result["files"]) if error is None else 0})
            if error is None:
                say(f"iris-batch: {name}: {len(result['files'])} files in "
                    f"{result['seconds']:.1f} s")
            else:
                failed.append(name)
                print(f"iris-batch: {name}: FAILED: {error}", file=sys.stderr)
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    atomic_write_json(out / "batch.json", {"scenes": report, "failed": failed,
                                           "seconds": round(time.perf_counter() - t0, 3),
                                           "ray": args.ray})
    say(f"iris-batch: {len(scenes) - len(failed)} of {len(scenes)} scene(s) rendered into {out} "
        f"in {time.perf_counter() - t0:.1f} s" + (f"; failed: {', '.join(failed)}" if failed
                                                  else ""))
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return run(args)
    except (IrisError, OSError) as exc:
        print(f"iris-batch: error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}",
              file=sys.stderr)
        return cli.EXIT_ERROR
    except KeyboardInterrupt:
        print("iris-batch: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

"""Meshes of real objects that registry packages ship, for the capture kinds' "packaged" shapes.

* PyPI ``pybullet`` (zlib licence): ``pybullet_data`` holds a duck, the Stanford bunny, a mug, a
  teddy bear, a Lego brick, a football, toys, and 1000 random graspable objects
  (``random_urdfs/NNN/NNN.obj``).
* Debian ``assimp-testmodels`` (BSD-3-Clause): the Wuson boar and a spider.
Meshes are loaded on first use (one at a time, cached) and normalised; nothing is downloaded. The
pool is fixed: a missing file raises, naming the package to install, because the scenes depend
on it.
"""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

#: Named pybullet_data meshes (z up), then the 1000 random objects.
PYBULLET_NAMED = ("duck.obj", "bunny.obj", "urdf/mug.obj", "lego/lego.obj", "teddy2_VHACD_CHs.obj",
                  "torus/torus_textured.obj", "soccerball.obj", "domino/domino.obj",
                  "jenga/jenga.obj", "toys/shape_sorter.obj", "toys/concave_box.obj")
PYBULLET_RANDOM = tuple(f"random_urdfs/{i:03d}/{i:03d}.obj" for i in range(1000))
#: assimp-testmodels meshes (y up: turned to z up).
ASSIMP_DIR = Path("/usr/share/assimp/models")
ASSIMP_NAMED = ("OFF/Wuson.off", "OBJ/spider.obj")
#: Share of draws from the named objects (the rest: pybullet's random objects).
NAMED_SHARE = 0.4


def _pybullet_dir() -> Path:
    try:
        import pybullet_data
    except ImportError:
        raise RuntimeError("the capture kinds' packaged meshes need the PyPI package pybullet "
                           "(pip install pybullet==3.2.7)") from None
    return Path(pybullet_data.getDataPath())


@functools.lru_cache(maxsize=256)
def load_mesh(source: str, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices [N, 3] float64, faces [F, 3] int64)`` of a pooled mesh, z up, consistently
    wound, centred and scaled to a bounding radius of 1."""
    import trimesh

    if source == "pybullet":
        path, y_up, package = _pybullet_dir() / name, False, "pybullet (pip install pybullet==3.2.7)"
    else:
        path, y_up, package = ASSIMP_DIR / name, True, "assimp-testmodels (apt-get install assimp-testmodels)"
    if not path.is_file():
        raise RuntimeError(f"mesh {path} is missing: the capture kinds need the package {package}")
    mesh = trimesh.load(str(path), force="mesh", process=True)
    trimesh.repair.fix_normals(mesh)
    v = np.asarray(mesh.vertices, np.float64)
    if y_up:
        v = v[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])   # (x, y, z) -> (x, -z, y): a rotation
    v = v - 0.5 * (v.min(0) + v.max(0))
    v = v / max(np.linalg.norm(v, axis=1).max(), 1e-12)
    return v, np.asarray(mesh.faces, np.int64)


def random_packaged(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, str]:
    """A random pooled mesh -> ``(vertices, faces, name)``."""
    if rng.random() < NAMED_SHARE:
        named = [("pybullet", n) for n in PYBULLET_NAMED] + [("assimp", n) for n in ASSIMP_NAMED]
        source, name = named[int(rng.integers(len(named)))]
    else:
        source, name = "pybullet", PYBULLET_RANDOM[int(rng.integers(len(PYBULLET_RANDOM)))]
    v, f = load_mesh(source, name)
    return v, f, name

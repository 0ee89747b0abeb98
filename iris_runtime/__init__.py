"""IRIS runtime: render novel views from an exported IRIS model with ONNX Runtime, no torch.

    from iris_runtime import IrisRuntime
    rt = IrisRuntime("out/")                     # checks iris.json and the graphs' sha256
    image = rt.render(images, pose)              # uint8 [H, W, 3]
    scene = rt.encode(images)                    # encode once ...
    result = rt.render(scene, 1, depth=True)     # ... render many poses (here: input view 1's)

Rendering, module by module: ``runtime`` (``IrisRuntime``: sessions, encoder, argument checks; a
thin facade) -> ``raymarch`` (``MarchPlan`` and the ray loop up to ``session.run``) ->
``geometry`` (numpy camera maths) and ``quality`` (the speed knobs, view selection). Value types:
``scene`` (``Scene``, ``RenderResult``); request limits and the memory model: ``limits``.

Dependencies: numpy, onnxruntime, Pillow, OpenCV. Never torch (a test imports this package with
torch blocked).
"""
from .errors import (ImageError, InputError, IrisError, ManifestError, ModelFileError,
                     ModelFormatError, ModelIntegrityError)
from .runtime import IrisRuntime, RenderResult, Scene
from .quality import QUALITY_PRESETS, RenderSettings

__all__ = ["IrisRuntime", "Scene", "RenderResult", "RenderSettings", "QUALITY_PRESETS",
           "IrisError", "InputError", "ImageError", "ModelFileError", "ManifestError",
           "ModelFormatError", "ModelIntegrityError"]

"""Typed errors of IRIS. Every error raised on purpose by the package derives from ``IrisError``.

Each error also derives from the built-in exception a caller would naturally catch (``ValueError``
for bad arguments, ``OSError`` for a bad model file), so ``except ValueError`` keeps working.
Messages name the argument (or file) and say what was expected and what was found.
"""
from __future__ import annotations


class IrisError(Exception):
    """Base class of every error IRIS raises on purpose."""


class ImageError(IrisError, ValueError):
    """An image argument or file is unreadable, truncated, empty or of an unsupported kind."""


class InputError(IrisError, ValueError):
    """An argument or input file has the wrong shape, dtype, value or content (not an image)."""


class ModelFileError(IrisError, OSError):
    """A model file is missing, tampered with, or of an unsupported format version."""


class ManifestError(ModelFileError):
    """The model's manifest (``iris.json``) is missing, not JSON, lacks or mis-types a field, or
    names a file outside the model directory."""


class ModelFormatError(ModelFileError):
    """The manifest's format name or version is not the one this runtime reads."""


class ModelIntegrityError(ModelFileError):
    """A graph file does not match the sha256 recorded in the manifest (tampered or truncated)."""


__all__ = ["IrisError", "ImageError", "InputError", "ModelFileError", "ManifestError",
           "ModelFormatError", "ModelIntegrityError"]

"""Small file I/O shared by the runtime, the exporter and the trainer (torch-free).

- ``atomic_write`` (a callback writes a binary file object, e.g. ``torch.save``) and
  ``atomic_write_bytes`` / ``atomic_write_text`` / ``atomic_write_json``: write through a
  temporary file in the same folder and ``os.replace``, so readers see the old file or the new
  one, never half of one. JSON is strict (``allow_nan=False``: NaN/Infinity are not JSON).
- ``read_text`` / ``read_json``: a file's UTF-8 text / top-level JSON object; every failure
  (missing, unreadable, not JSON, not an object) is the caller's typed error naming the file.
- ``sha256_file`` / ``sha256_bytes``: hex digests (what the manifest records per graph).
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable

from .errors import InputError

__all__ = ["atomic_write", "atomic_write_bytes", "atomic_write_text", "atomic_write_json", "read_text",
           "read_json", "sha256_file", "sha256_bytes"]

_CHUNK = 1 << 20


def _umask() -> int:
    """The process's umask, read without changing it where the OS allows (``os.umask`` can only
    be read by setting it, which races with other threads creating files)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], object]) -> None:
    """Call ``write(f)`` on a temporary file in ``path``'s folder (created if needed), then
    ``os.replace`` it onto ``path``: readers see the old file or the new one, never half of one,
    and a failure (an exception from ``write``, Ctrl-C) leaves ``path`` as it was and no
    temporary file behind. The new file gets the permissions of a plain ``open(path, "w")``
    (0666 minus the umask), not ``mkstemp``'s 0600."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """``atomic_write`` of ``data``."""
    atomic_write(path, lambda f: f.write(data))


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """``atomic_write_bytes`` of UTF-8 text with Unix newlines."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj, *, indent: int | None = 2) -> None:
    """``obj`` as strict JSON (``allow_nan=False``: a NaN or infinity is a ``ValueError``, not a
    file other JSON readers refuse) plus a final newline, written atomically."""
    atomic_write_text(path, json.dumps(obj, indent=indent, allow_nan=False) + "\n")


def read_text(path: str | os.PathLike, *, what: str = "",
              error: type[Exception] = InputError) -> str:
    """UTF-8 text of ``path``; a missing or unreadable file is ``error`` naming it (and, when
    missing, what it should be: ``what``, e.g. ``"the iris.json manifest written by iris-export"``)."""
    path = Path(path)
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        expected = f" (expected {what})" if what else ""
        raise error(f"{path}: no such file{expected}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise error(f"{path}: cannot read: {e}") from None


def read_json(path: str | os.PathLike, *, what: str = "",
              error: type[Exception] = InputError) -> dict:
    """The JSON object in ``path``; every failure (missing, unreadable, not JSON, not an object)
    is ``error`` naming the file (see ``read_text`` for ``what``)."""
    text = read_text(path, what=what, error=error)
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise error(f"{path}: not valid JSON ({e})") from None
    if not isinstance(doc, dict):
        raise error(f"{path}: expected a JSON object at the top level")
    return doc


def sha256_bytes(data: bytes) -> str:
    """Hex sha256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | os.PathLike) -> str:
    """Hex sha256 of the file at ``path``, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()

"""iris_runtime.fileio (atomic writes, typed JSON reads, sha256) and the one declaration of the
export/runtime contract (iris_runtime.io_spec). Torch-free."""
from __future__ import annotations

import hashlib
import json
import os

import pytest

from iris_runtime import fileio, io_spec
from iris_runtime.errors import InputError, ManifestError


def test_atomic_write_replaces_whole_files_with_plain_permissions(tmp_path):
    path = tmp_path / "sub" / "a.bin"
    fileio.atomic_write_bytes(path, b"one")
    fileio.atomic_write_bytes(path, b"two")
    assert path.read_bytes() == b"two"
    assert [p.name for p in path.parent.iterdir()] == ["a.bin"]
    umask = os.umask(0o022)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask        # not mkstemp's 0600
    fileio.atomic_write_text(tmp_path / "t.txt", "é\n")
    assert (tmp_path / "t.txt").read_bytes() == "é\n".encode("utf-8")


def test_atomic_write_failure_keeps_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "a.bin"
    fileio.atomic_write_bytes(path, b"old")

    def fail(f):
        f.write(b"half")
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        fileio.atomic_write(path, fail)
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


def test_atomic_write_json_is_strict(tmp_path):
    path = tmp_path / "r.json"
    fileio.atomic_write_json(path, {"a": [1.5, None]})
    assert path.read_text() == json.dumps({"a": [1.5, None]}, indent=2) + "\n"
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError):
            fileio.atomic_write_json(path, {"a": bad})
    assert json.loads(path.read_text()) == {"a": [1.5, None]}
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


@pytest.mark.parametrize("content, match", [
    (None, "no such file"),
    (b"{not json", "not valid JSON"),
    (b"[1, 2]", "JSON object"),
    (b"\xff\xfe\x00", "cannot read"),
])
def test_read_json_errors_are_typed_and_name_the_file(tmp_path, content, match):
    path = tmp_path / "x.json"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputError, match=match) as info:
        fileio.read_json(path)
    assert str(path) in str(info.value)
    with pytest.raises(ManifestError, match=match):
        fileio.read_json(path, error=ManifestError)


def test_read_json_says_what_a_missing_file_should_be(tmp_path):
    with pytest.raises(ManifestError, match=r"no such file \(expected the manifest\)"):
        fileio.read_json(tmp_path / "iris.json", what="the manifest", error=ManifestError)
    (tmp_path / "ok.json").write_text('{"a": 1}')
    assert fileio.read_json(tmp_path / "ok.json") == {"a": 1}


def test_sha256(tmp_path):
    data = os.urandom(3 * (1 << 20) + 17)           # several read chunks
    (tmp_path / "f").write_bytes(data)
    assert fileio.sha256_file(tmp_path / "f") == fileio.sha256_bytes(data) \
        == hashlib.sha256(data).hexdigest()


def test_the_contract_is_declared_once():
    """export.io_spec re-exports the runtime's spec objects; the runtime's manifest reader
    requires exactly the spec's names and dtypes."""
    from export import io_spec as export_spec
    from iris_runtime import manifest

    for name in ("ENCODER", "RENDERER", "GRAPHS", "EXPLICIT_RGB_INPUTS", "EXPLICIT_RGB_AXES",
                 "IO_SPEC_VERSION", "spec_for"):
        assert getattr(export_spec, name) is getattr(io_spec, name)
    for explicit_rgb in (False, True):
        required = manifest.required_io_for(explicit_rgb)
        for graph in io_spec.GRAPHS:
            spec = io_spec.spec_for(graph, explicit_rgb)
            for kind in ("inputs", "outputs"):
                assert required[graph][kind] == {n: e["dtype"] for n, e in spec[kind].items()}
    assert "colours" in manifest.required_io_for(True)["renderer"]["inputs"]
    assert "colours" not in manifest.required_io_for(False)["renderer"]["inputs"]
    assert manifest.MANIFEST_NAME == io_spec.MANIFEST_NAME == "iris.json"

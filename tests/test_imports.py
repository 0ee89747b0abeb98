"""The packages stay a codebase one can read: no import circle between their modules, no file over
``MAX_LINES`` lines, and every module importable on its own.

The circle check parses every module of ``iris_runtime``, ``export`` and ``iris_train`` with ``ast``
(no import runs) and follows each import of one of those modules, those inside functions included:
a deferred import that only dodges a circle is still a circle (move the shared piece into a module
both import). Importing a module alone catches what parsing cannot: a module that works only when
another one happened to be imported first. Each module is imported in a child process forked from
one that has loaded the third-party libraries (torch, onnx, OpenCV ...) once, so the project's
modules start from nothing each time and the whole check takes seconds, not a torch import per
module.
"""
from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("iris_runtime", "export", "iris_train")
MAX_LINES = 500

def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _all_modules() -> dict[str, Path]:
    """Every module of the packages by dotted name."""
    return {_module_name(path): path
            for path in sorted(p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py"))}


def _modules() -> dict[str, Path]:
    """Every module of the packages by dotted name, the ones being split left out."""
    return _all_modules()


def _imports(module: str, path: Path, modules) -> dict[str, int]:
    """The project modules ``module`` imports (anywhere in its file) -> the line of the first.

    ``from . import x`` imports the submodule x (its package is already being initialised: not an
    edge to the package); ``from .x import y`` imports x, or x.y when that is a module."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: dict[str, int] = {}

    def add(name: str, line: int) -> None:
        while name and name not in modules:          # an attribute of a module: the module
            name = name.rpartition(".")[0]
        if name and name != module:
            found.setdefault(name, line)

    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name, node.lineno)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            for alias in node.names:
                add(f"{source}.{alias.name}" if f"{source}.{alias.name}" in modules else source,
                    node.lineno)
    return found


def _cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """One cycle of each strongly connected component of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(set(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    cycles = []
    for component in components:     # walk inside the component from its first module back
        start = min(component)
        path, seen = [start], {start}
        while True:
            nxt = min(w for w in graph[path[-1]] if w in component)
            if nxt in seen:
                cycles.append(path[path.index(nxt):] + [nxt])
                break
            path.append(nxt)
            seen.add(nxt)
    return cycles


def test_no_package_file_is_over_the_line_limit():
    long = {str(path.relative_to(REPO)): n for path in _modules().values()
            if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_LINES}
    assert not long, f"files over {MAX_LINES} lines (split them by what they do): {long}"


def test_no_import_circle_between_the_packages_modules():
    every, modules = _all_modules(), _modules()
    graph = {name: {m: line for m, line in _imports(name, path, every).items()
                    if m in modules} for name, path in modules.items()}
    cycles = _cycles(graph)
    described = [" -> ".join(f"{a} (line {graph[a][b]})" for a, b in zip(c, c[1:])) + f" -> {c[-1]}"
                 for c in cycles]
    assert not cycles, "import circles (imports inside functions count):\n" + "\n".join(described)


def test_the_circle_check_sees_a_deferred_circle(tmp_path):
    # The check itself: a circle closed by an import inside a function is found.
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text("from b import f\n")
    b.write_text("def f():\n    from a import g\n")
    modules = {"a": a, "b": b}
    graph = {name: _imports(name, path, modules) for name, path in modules.items()}
    assert _cycles(graph) == [["a", "b", "a"]]


_IMPORT_ALONE = textwrap.dedent("""
    import importlib, json, os, sys, traceback
    modules, third_party, ours = json.loads(sys.argv[1])
    for name in third_party:            # loaded once here, shared by every child
        try:
            importlib.import_module(name)
        except Exception:
            pass
    loaded = [m for m in sys.modules if m.split(".")[0] in ours]
    assert not loaded, f"a third-party import loaded project modules: {loaded}"

    def child(module):
        try:
            importlib.import_module(module)
            return "ok"
        except ModuleNotFoundError as exc:  # a library this environment lacks: not ours
            missing = (exc.name or "").split(".")[0]
            if missing and missing not in ours:
                return f"skip: no {exc.name}"
            return traceback.format_exc()
        except BaseException:
            return traceback.format_exc()

    results, running, pending = {}, {}, list(modules)
    jobs = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1
    while pending or running:
        while pending and len(running) < jobs:
            module = pending.pop(0)
            read, write = os.pipe()
            pid = os.fork()
            if pid == 0:
                os.close(read)
                # Within the pipe's buffer, so that the child never waits for the reader.
                os.write(write, child(module).encode()[-32768:])
                os._exit(0)
            os.close(write)
            running[pid] = (module, read)
        pid, _ = os.wait()
        module, read = running.pop(pid)
        with os.fdopen(read, "rb") as f:
            results[module] = f.read().decode(errors="replace")
    print(json.dumps(results))
""")


def _third_party(modules: dict[str, Path]) -> list[str]:
    """The libraries the modules import at their top level (what every child would load)."""
    names = set()
    for path in modules.values():
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.Import):
                names |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                names.add(node.module)
    return sorted(n for n in names if n.split(".")[0] not in PACKAGES and n != "__future__")


@pytest.mark.skipif(not hasattr(os, "fork"), reason="imports each module in a forked process")
def test_every_module_imports_alone(tmp_path):
    modules = {name: path for name, path in _modules().items()
               if path.name != "__main__.py"}             # importing one runs its command
    # The children share their bytecode through a cache of their own (the first one compiles a
    # module, the others read it), written outside the work tree.
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env.update(OMP_NUM_THREADS="1", PYTHONPYCACHEPREFIX=str(tmp_path / "pycache"))
    proc = subprocess.run(
        [sys.executable, "-c", _IMPORT_ALONE,
         json.dumps([sorted(modules), _third_party(modules), list(PACKAGES)])],
        cwd=REPO, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads(proc.stdout.strip().splitlines()[-1])
    failed = {m: r for m, r in results.items() if r != "ok" and not r.startswith("skip:")}
    assert not failed, "modules that fail to import alone:\n" + "\n".join(
        f"{m}:\n{r}" for m, r in failed.items())
    imported = [m for m, r in results.items() if r == "ok"]
    assert any(m.startswith("iris_runtime.") for m in imported), results

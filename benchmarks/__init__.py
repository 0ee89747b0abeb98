"""Benchmarks (not shipped: ``pyproject.toml`` packages only iris_train, iris_runtime and export).

A package so that the benchmarks' helper processes run as real modules
(``python -m benchmarks.evt.child ...``); each benchmark still runs as a script,
``python benchmarks/<name>.py``.
"""

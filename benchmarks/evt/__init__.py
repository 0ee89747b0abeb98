"""The pieces of ``benchmarks/error_vs_time.py`` (the command line and the run order live there).

- ``rows``:    the names of the table's rows and groups, the knob grid, the scaling and sizing
               grids.
- ``machine``: facts about the machine and the graph: versions, matmul peak, renderer FLOPs,
               ORT's per-op profile.
- ``measure``: the measured parts (knobs, scaling, sizing, peak, memory), timing and scene
               helpers.
- ``child``:   the subprocess entries (the tcmalloc torch anchor, the fresh-process memory
               measurement), run as ``python -m benchmarks.evt.child <part> ...``.
- ``targets``: the speed, error and memory targets, checked against a run's results.
- ``report``:  the results files (JSON, markdown table, plot).

Nothing here imports torch at module level: the memory child must stay a torch-free process.
"""

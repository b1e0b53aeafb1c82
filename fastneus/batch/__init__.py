"""Many scans: train a list of scenes, one run folder each, on local GPUs / CPU workers or on Ray.

- :mod:`fastneus.batch.plan`: scenes from the command line, run folder names, what each run needs
  (skip, resume, train), progress and errors read from the run folder;
- :mod:`fastneus.batch.local`: one worker per GPU (or CPU workers), each a ``fastneus train`` subprocess;
- :mod:`fastneus.batch.cluster`: the same runs as Ray tasks (the optional extra ``fastneus[ray]``);
- :mod:`fastneus.batch.board`: the live table, the summary table and ``summary.json``;
- :mod:`fastneus.batch.runner`: :func:`run_batch`, the whole batch.

Every run is a ``python -m fastneus train`` process, so a batch trains exactly as ``train`` does.
"""
from __future__ import annotations

from fastneus.batch.runner import BatchOptions, run_batch

__all__ = ["BatchOptions", "run_batch"]

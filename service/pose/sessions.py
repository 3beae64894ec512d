"""One place that decides how onnxruntime sessions are built, so the detector and the pose model agree.

Why these options:
- CPU provider only: the service targets plain CPU hosts; a GPU build of onnxruntime would be a deployment choice.
- intra-op threads default to the machine's cores (the detector); MoveNet's concurrent crop mode instead gives its
  session one thread and runs as many crops at once as there are cores (movenet.py). Inter-op 1, because these
  graphs are sequential chains and a second pool only competes for the same cores.
- spinning off: onnxruntime's workers busy-wait between kernels by default, which wins a few percent on an idle
  machine but, on a host shared with the API, the store and other workers, burns the cores other processes need
  and made a 15-crop batch up to ten times slower in our measurements (see bench/pose.py).
- full graph optimisation: constant folding, conv fusions and (only at this level) the NCHWc blocked layout:
  MoveNet Thunder takes ~19 ms of one core per crop with it and ~37 ms at the `extended` level.
"""

from __future__ import annotations

import os
from pathlib import Path

import onnxruntime as ort

PROVIDERS = ["CPUExecutionProvider"]


def default_threads() -> int:
    """Cores this process may run on (respects affinity masks and container CPU sets), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def session_options(threads: int | None = None, *, spinning: bool = False) -> ort.SessionOptions:
    """Options shared by every session of the pipeline (see the module docstring)."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads or default_threads()
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.log_severity_level = 3  # warnings about pruned initialisers of the converted graphs are noise
    options.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    return options


def make_session(model: Path | bytes, threads: int | None = None, *, spinning: bool = False) -> ort.InferenceSession:
    """A CPU session on a file or on serialised model bytes (a graph edited in memory)."""
    source = str(model) if isinstance(model, Path) else model
    return ort.InferenceSession(source, session_options(threads, spinning=spinning), providers=PROVIDERS)

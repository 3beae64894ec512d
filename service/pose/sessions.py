"""One place that decides how inference sessions are built, so the detector and the pose model agree.

Two runtimes run the same ONNX files:

- onnxruntime (the detector always; MoveNet where OpenVINO cannot do better), float32 on the CPU provider:
  - intra-op threads default to the machine's cores (the detector); MoveNet's concurrent crop mode instead gives
    its session one thread and runs as many crops at once as there are cores (movenet.py). Inter-op 1, because
    these graphs are sequential chains and a second pool only competes for the same cores.
  - spinning off: onnxruntime's workers busy-wait between kernels by default, which wins a few percent on an idle
    machine but, on a host shared with the API, the store and other workers, burns the cores other processes need
    and made a 15-crop batch up to ten times slower in our measurements (see bench/pose.py).
  - full graph optimisation: constant folding, conv fusions and (only at this level) the NCHWc blocked layout:
    MoveNet Thunder takes ~19 ms of one core per crop with it and ~37 ms at the `extended` level.
- OpenVINO, for MoveNet on CPUs with native bfloat16 arithmetic (AMX or AVX512-BF16: Intel Xeon since Sapphire
  Rapids). There a Lightning crop takes ~2.9 ms of one core instead of ~6.4 and a Thunder crop ~10 instead of ~24,
  while the keypoints move no more than the float model's own do when its crop is shifted by one image pixel
  (docs/benchmarks/pose.md, "bfloat16 pose"). onnxruntime's CPU provider has no bfloat16 kernels on x86, and
  OpenVINO in float32 is no faster than onnxruntime. The detector stays on onnxruntime in float32: in bfloat16
  its borderline boxes (scores near the 0.3 threshold) change, and two seated people of the atrium annotation
  were lost (14 -> 12 of 22).

`PoseRuntime` `auto` picks OpenVINO where the CPU has native bfloat16 and onnxruntime elsewhere, so a host without
it runs exactly the float32 pipeline. Load-time checks that an edited graph computes what the file does compare
graphs, not precisions: they run on onnxruntime (movenet.py).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol

import numpy as np
import onnxruntime as ort

if TYPE_CHECKING:
    import openvino as ov

PROVIDERS = ["CPUExecutionProvider"]
PoseRuntime = Literal["auto", "onnxruntime", "openvino"]
Runtime = Literal["onnxruntime", "openvino"]


class _Named(Protocol):
    name: str


class Session(Protocol):
    """What the pipeline asks of a session: onnxruntime's `InferenceSession` interface, as far as it is used."""

    def get_inputs(self) -> Sequence[_Named]: ...

    def run(self, output_names: Sequence[str] | None, input_feed: dict[str, np.ndarray]) -> list[np.ndarray]: ...


def default_threads() -> int:
    """Cores this process may run on (respects affinity masks and container CPU sets), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def thread_pool(workers: int) -> ThreadPoolExecutor:
    """This process's pool of `workers` threads for session calls run side by side (person crops, detector
    regions); rebuilt in a forked child, where an inherited pool's threads do not exist."""
    key = (os.getpid(), workers)
    pool = _POOLS.get(key)
    if pool is None:
        pool = _POOLS[key] = ThreadPoolExecutor(workers, thread_name_prefix="inference")
    return pool


_POOLS: dict[tuple[int, int], ThreadPoolExecutor] = {}


@cache
def native_bf16() -> bool:
    """Whether OpenVINO is installed and this CPU computes in bfloat16 natively (OpenVINO's own capability list)."""
    try:
        import openvino  # noqa: F401
    except ImportError:
        return False
    return "BF16" in _core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")


_forked_jobs = False


def serve_forked_jobs() -> None:
    """This process will fork a child per job that runs the sessions it built (a `--fork` worker): from now on
    `auto` means onnxruntime, and `openvino` is refused. OpenVINO's thread pools do not survive fork: a child's
    first inference waits forever for threads that exist only in the parent."""
    global _forked_jobs
    _forked_jobs = True


def resolve_runtime(choice: PoseRuntime) -> Runtime:
    """The runtime MoveNet runs on for a `pose_runtime` setting (see the module docstring)."""
    if choice == "auto":
        return "openvino" if native_bf16() and not _forked_jobs else "onnxruntime"
    if choice == "openvino":
        if _forked_jobs:
            raise ValueError(
                "pose_runtime 'openvino' cannot serve a worker that forks a child per job (its thread pools do not "
                "survive fork): run the worker without --fork, or set POSEMETRY_POSE_RUNTIME=onnxruntime or auto"
            )
        try:
            import openvino  # noqa: F401
        except ImportError as exc:
            raise ValueError("pose_runtime 'openvino' needs the openvino package (pip install openvino)") from exc
    return choice


def session_options(threads: int | None = None, *, spinning: bool = False) -> ort.SessionOptions:
    """onnxruntime options shared by every session of the pipeline (see the module docstring)."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads or default_threads()
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.log_severity_level = 3  # warnings about pruned initialisers of the converted graphs are noise
    options.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    return options


def make_session(
    model: Path | bytes,
    threads: int | None = None,
    *,
    spinning: bool = False,
    runtime: Runtime = "onnxruntime",
    streams: int = 1,
) -> Session:
    """A CPU session on a file or on serialised model bytes (a graph edited in memory).

    `streams`: how many threads will call `run` at once, each wanting `threads` cores (onnxruntime runs each call
    on the caller's thread and its own intra-op pool, so only OpenVINO needs to know).
    """
    if runtime == "openvino":
        return OpenVINOSession(model, threads or default_threads(), streams=streams)
    source = str(model) if isinstance(model, Path) else model
    return ort.InferenceSession(source, session_options(threads, spinning=spinning), providers=PROVIDERS)


class _Input:
    def __init__(self, name: str) -> None:
        self.name = name


class OpenVINOSession:
    """An OpenVINO compiled model behind onnxruntime's `run` interface, safe to call from several threads at once.

    A compiled model executes requests on "streams"; each calling thread gets its own infer request, and the model
    is compiled with one stream per concurrent caller (`streams`), each of `threads` cores, so concurrent crops
    run side by side instead of queueing on one stream. A model with a fixed input shape (MoveNet) is compiled for
    it; one with a symbolic shape keeps it symbolic (one compilation, not one per shape).
    """

    def __init__(self, model: Path | bytes, threads: int, *, streams: int = 1) -> None:
        core = _core()
        graph = core.read_model(str(model)) if isinstance(model, Path) else core.read_model(model, b"")
        config: dict[str, Any] = {
            "NUM_STREAMS": max(1, streams),
            "INFERENCE_NUM_THREADS": max(1, threads) * max(1, streams),
            "INFERENCE_PRECISION_HINT": "bf16" if native_bf16() else "f32",
            # Pinned threads cannot move off a core the API or another worker is using: on a shared host, no.
            "ENABLE_CPU_PINNING": False,
        }
        if streams <= 1:
            config["PERFORMANCE_HINT"] = "LATENCY"
        self._compiled: ov.CompiledModel = core.compile_model(graph, "CPU", config)
        self._inputs = [_Input(port.get_any_name()) for port in graph.inputs]
        self._outputs = {name: port for port in self._compiled.outputs for name in port.get_names()}
        self._local = threading.local()
        self._pid = os.getpid()

    def get_inputs(self) -> Sequence[_Named]:
        return self._inputs

    def run(self, output_names: Sequence[str] | None, input_feed: dict[str, np.ndarray]) -> list[np.ndarray]:
        if os.getpid() != self._pid:  # a forked child would wait forever for the parent's threads
            raise RuntimeError("an OpenVINO session cannot run in a process forked after it was built")
        request = getattr(self._local, "request", None)
        if request is None:
            request = self._local.request = self._compiled.create_infer_request()
        if _first_inference.is_set():
            return self._infer(request, output_names, input_feed)
        # OpenVINO's Python binding initialises its numpy bridge (a pybind11 call-once) on the first tensor it
        # reads, and two threads doing that at once deadlock for good (the GIL against the once-flag; 3 fresh
        # processes in 20 hung a pose worker's first frame). The process's first inference runs alone.
        with _first_inference_lock:
            results = self._infer(request, output_names, input_feed)
            _first_inference.set()
            return results

    def _infer(
        self, request: ov.InferRequest, output_names: Sequence[str] | None, input_feed: dict[str, np.ndarray]
    ) -> list[np.ndarray]:
        results = request.infer(input_feed)
        names = output_names or [port.get_any_name() for port in self._compiled.outputs]
        # Copies: the request reuses its output buffers on the next call.
        return [np.array(results[self._outputs[name]]) for name in names]


_first_inference = threading.Event()
_first_inference_lock = threading.Lock()


@cache
def _core() -> ov.Core:
    import openvino as ov

    return ov.Core()

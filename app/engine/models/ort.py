"""The one place that builds onnxruntime sessions (thread counts, arena, providers).

Why one place: session options decide latency and memory for every model, and a second ad-hoc
``InferenceSession`` elsewhere would silently ignore them. The thread count comes from the process's
settings (``Settings.ort_threads``, given once at start by ``set_session_threads``), never from the
environment here; onnxruntime itself is imported with the first session, so the CLI starts without it.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import onnxruntime

#: Intra-op threads of a session made without its own count; 0 lets onnxruntime use every core.
_session_threads = 0


def set_session_threads(threads: int) -> None:
    """The threads of every session made from now on without its own count (0: every core). Called once per
    process by its entry point (``geoloc``'s ``main``, a Ray actor holding N CPUs) before any model loads."""
    global _session_threads
    if threads < 0:
        raise ValueError(f"onnxruntime threads must be 0 (every core) or more, not {threads}")
    _session_threads = threads


def create_session(model_path: Path, intra_threads: int | None = None) -> onnxruntime.InferenceSession:
    """CPU session; ``intra_threads`` defaults to the process's count (``set_session_threads``)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = intra_threads or _session_threads  # 0 lets onnxruntime use every core
    opts.inter_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # Input sizes vary per photo: the arena would keep the largest allocation forever.
    opts.enable_cpu_mem_arena = False
    opts.log_severity_level = 3
    # Spinning worker threads would keep burning both cores after each run, slowing the stages after it.
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(str(model_path), sess_options=opts, providers=["CPUExecutionProvider"])

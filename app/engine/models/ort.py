"""The one place that builds onnxruntime sessions (thread counts, arena, providers).

Why one place: session options decide latency and memory for every model, and a second ad-hoc
``InferenceSession`` elsewhere would silently ignore them.
"""

from __future__ import annotations

import os
from pathlib import Path

import onnxruntime as ort


def create_session(model_path: Path, intra_threads: int | None = None) -> ort.InferenceSession:
    """CPU session; ``intra_threads`` defaults to ``GEOLOC_ORT_THREADS`` or all cores."""
    opts = ort.SessionOptions()
    threads = intra_threads or int(os.environ.get("GEOLOC_ORT_THREADS", "0"))
    opts.intra_op_num_threads = threads  # 0 lets onnxruntime use every core
    opts.inter_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # Input sizes vary per photo: the arena would keep the largest allocation forever.
    opts.enable_cpu_mem_arena = False
    opts.log_severity_level = 3
    # Spinning worker threads would keep burning both cores after each run, slowing the stages after it.
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(str(model_path), sess_options=opts, providers=["CPUExecutionProvider"])

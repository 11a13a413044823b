"""Search the reference codes: float (inner product), binary (Hamming) or two-stage.

Two-stage takes a Hamming shortlist (cheap, approximate) and re-scores only the shortlist exactly with
the float codes: most of the float accuracy at binary speed (METHOD.md, "Search"). A configuration with
both kinds of codes keeps both for every reference, so any of the three modes can be asked for.
"""

from __future__ import annotations

import numpy as np

from app.engine.configs import CONFIGS, PipelineConfig
from app.engine.errors import GeolocError
from app.engine.index.vectors import VectorIndex


class UnsupportedMode(GeolocError):
    pass


#: Every search mode some configuration can serve.
SEARCH_MODES = ("float", "binary", "two-stage")


def unsupported_mode_message(mode: str, config: PipelineConfig) -> str:
    """Why ``mode`` cannot be served, and what would serve it: the named configurations that can (a user who
    asks for binary search on the float-only default needs to know which configuration to start instead)."""
    served = ", ".join(config.modes)
    if mode not in SEARCH_MODES:
        return f"mode {mode!r} is not a search mode (float, binary or two-stage); {config.name!r} serves {served}"
    others = [name for name, c in CONFIGS.items() if mode in c.modes]
    return (
        f"mode {mode!r} is not available for configuration {config.name!r}, which serves {served}; the named "
        f"configurations that serve {mode} are {', '.join(others)} (fit one with `make fit CONFIG=NAME`, then "
        "serve it with GEOLOC_CONFIG=NAME or --config NAME)"
    )


class ReferenceIndex:
    def __init__(self, config: PipelineConfig, float_dim: int | None, bits: int | None):
        self.config = config
        self.float = VectorIndex(float_dim, False, config.float_index) if float_dim else None
        self.binary = VectorIndex(bits, True, config.binary_index) if bits else None

    @property
    def size(self) -> int:
        idx = self.float or self.binary
        return idx.ntotal if idx is not None else 0

    def add(self, ids: np.ndarray, float_codes: np.ndarray | None, binary_codes: np.ndarray | None) -> None:
        if self.float is not None:
            self.float.add(ids, float_codes)
        if self.binary is not None:
            self.binary.add(ids, binary_codes)

    def remove(self, ids) -> int:
        n = 0
        for idx in (self.float, self.binary):
            if idx is not None:
                n = idx.remove(ids)
        return n

    def compact(self) -> None:
        for idx in (self.float, self.binary):
            if idx is not None:
                idx.compact()

    @property
    def tombstones(self) -> int:
        idx = self.float or self.binary
        return len(idx.tombstones) if idx is not None else 0

    def check_mode(self, mode: str | None) -> str:
        """The mode to use: the configuration's best when None; an error naming the choices otherwise."""
        modes = self.config.modes
        if mode is None:
            return modes[0]
        if mode not in modes:
            raise UnsupportedMode(unsupported_mode_message(mode, self.config))
        return mode

    def search(
        self,
        float_code: np.ndarray | None,
        binary_code: np.ndarray | None,
        k: int,
        mode: str | None = None,
        allowed: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One query -> (scores, ids) of up to ``k`` references, best first, scores in [0, 1]."""
        mode = self.check_mode(mode)
        if mode == "float":
            s, i = self.float.search(float_code[None], k, allowed)
        elif mode == "binary":
            s, i = self.binary.search(binary_code[None], k, allowed)
        else:
            shortlist = max(self.config.shortlist, k)
            _, cand = self.binary.search(binary_code[None], shortlist, allowed)
            cand = cand[0][cand[0] >= 0]
            scores = self.float.score_ids(float_code, cand) if len(cand) else np.zeros(0, np.float32)
            order = np.argsort(-scores, kind="stable")[:k]
            s = np.zeros((1, k), np.float32)
            i = np.full((1, k), -1, np.int64)
            s[0, : len(order)], i[0, : len(order)] = scores[order], cand[order]
        valid = i[0] >= 0
        return s[0][valid], i[0][valid]

    def bytes_per_reference(self) -> float:
        """Code bytes one reference costs (float32 codes + packed bits), the figure eval reports."""
        b = 0
        if self.float is not None:
            b += 4 * self.float.dim
        if self.binary is not None:
            b += self.binary.dim // 8
        return float(b)

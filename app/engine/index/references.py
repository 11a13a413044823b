"""Search the reference codes: float (inner product), binary (Hamming) or two-stage.

Two-stage takes a Hamming shortlist (cheap, approximate) and re-scores only the shortlist exactly with
the float codes: most of the float accuracy at binary speed (method.md, "Search"). A configuration with
both kinds of codes keeps both for every reference, so any of the three modes can be asked for.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from app.engine.artifacts import atomic_write_file
from app.engine.configs import PipelineConfig
from app.engine.errors import GeolocError
from app.engine.index.base import VectorIndex, build_index
from app.engine.index.ivf_lists import MAX_POINTS_PER_LIST, default_nlist


class UnsupportedMode(GeolocError):
    pass


#: Every search mode some configuration can serve.
SEARCH_MODES = ("float", "binary", "two-stage")

#: The exact kind, and the compressed kind each part switches to at size (``ReferenceIndex.compressed``).
EXACT_KIND = "flat"
COMPRESSED_KINDS = {"float": "ivf-rabitq", "binary": "binary-ivf"}


def trained_file(part: str) -> str:
    """The file of a part's trained state in a fitted pipeline's folder (``ReferenceIndex.save_trained``)."""
    return f"index-{part}.faiss"


#: The named configurations that serve a search mode (``app.engine.configs.configs_serving``): given to an
#: index by whoever builds it, since the registry of named configurations sits above the index kinds.
Serving = Callable[[str], list[str]]


def unsupported_mode_message(mode: str, config: PipelineConfig, serving: Serving | None = None) -> str:
    """Why ``mode`` cannot be served, and what would serve it: the named configurations that can (a user who
    asks for binary search on the float-only default needs to know which configuration to start instead),
    when ``serving`` says which."""
    served = ", ".join(config.modes)
    if mode not in SEARCH_MODES:
        return f"mode {mode!r} is not a search mode (float, binary or two-stage); {config.name!r} serves {served}"
    refused = f"mode {mode!r} is not available for configuration {config.name!r}, which serves {served}"
    if serving is None:
        return refused
    return (
        f"{refused}; the named configurations that serve {mode} are {', '.join(serving(mode))} (fit one with "
        "`make fit CONFIG=NAME`, then serve it with GEOLOC_CONFIG=NAME or --config NAME)"
    )


class ReferenceIndex:
    """The pair a collection searches: a float and/or a binary ``VectorIndex`` of the same references, of
    the kinds the configuration names, built by ``build_index`` and used through the protocol only."""

    def __init__(
        self,
        config: PipelineConfig,
        float_dim: int | None,
        bits: int | None,
        kinds: dict[str, str] | None = None,
        params: dict[str, dict[str, Any]] | None = None,
        serving: Serving | None = None,
    ):
        """``kinds``: the part's kind by part name where it is not the configuration's (a snapshot of an index
        that switched by size, ``compressed``); ``params``: keyword arguments of a part's ``build_index``;
        ``serving``: which named configurations serve a mode, for the message refusing one this index cannot
        serve (``unsupported_mode_message``)."""
        self.config = config
        self.serving = serving
        kinds = {"float": config.float_index, "binary": config.binary_index, **(kinds or {})}
        params = params or {}
        self.float: VectorIndex | None = (
            build_index(kinds["float"], float_dim, False, **params.get("float", {})) if float_dim else None
        )
        self.binary: VectorIndex | None = (
            build_index(kinds["binary"], bits, True, **params.get("binary", {})) if bits else None
        )

    def parts(self) -> dict[str, VectorIndex]:
        """The indexes this one holds, by name (``float``, ``binary``): what snapshots write one file each of."""
        return {name: idx for name, idx in (("float", self.float), ("binary", self.binary)) if idx is not None}

    def _first(self) -> VectorIndex | None:
        return self.float or self.binary

    @property
    def size(self) -> int:
        idx = self._first()
        return idx.size if idx is not None else 0

    def ids(self) -> np.ndarray:
        """The live reference ids (both parts hold the same ones)."""
        idx = self._first()
        return idx.ids() if idx is not None else np.zeros(0, np.int64)

    def kinds(self) -> dict[str, str]:
        """Each part's serving kind."""
        return {name: idx.kind for name, idx in self.parts().items()}

    # -- the kind by size ----------------------------------------------------------------------------
    @property
    def switches_by_size(self) -> bool:
        """Whether this index may be replaced by ``compressed`` once the collection is large: the
        configuration lets the size choose (``index_by_size``) and names the exact kind for every part it
        has. A configuration that names another kind (``lite2-hybrid-384-ivf``) keeps it at every size."""
        c = self.config
        named = {"float": c.float_index, "binary": c.binary_index}
        return c.index_by_size and all(named[p] == EXACT_KIND for p in self.parts())

    @property
    def is_exact(self) -> bool:
        return all(kind == EXACT_KIND for kind in self.kinds().values())

    def sample(self, n: int, seed: int = 0) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Up to ``n`` live codes of each part, drawn reproducibly (the compressed kind's training sample);
        read from the exact (``flat``) index in place (``FlatIndex.sample``), one copy of the sample only."""
        if not self.is_exact:
            raise ValueError(f"only an exact index is sampled to train the compressed kinds, not {self.kinds()}")
        out = {name: idx.sample(n, seed) for name, idx in self.parts().items()}
        return out.get("float"), out.get("binary")

    def compressed(self, size: int, float_codes: np.ndarray | None, binary_codes: np.ndarray | None) -> ReferenceIndex:
        """A new, empty index of the compressed kinds (``COMPRESSED_KINDS``), trained on the collection's
        own codes (``sample``), with about 4 sqrt(``size``) lists (``default_nlist``). The caller fills it."""
        nlist = default_nlist(size)
        twin = ReferenceIndex(
            self.config,
            self.float.dim if self.float is not None else None,
            self.binary.dim if self.binary is not None else None,
            kinds={p: COMPRESSED_KINDS[p] for p in self.parts()},
            params={p: {"nlist": nlist} for p in self.parts()},
            serving=self.serving,
        )
        twin.train(float_codes, binary_codes)
        return twin

    @staticmethod
    def sample_size(size: int) -> int:
        """How many codes ``compressed`` trains on for a collection of ``size``: the most its lists use."""
        return default_nlist(size) * MAX_POINTS_PER_LIST

    # -- training -------------------------------------------------------------------------------------
    @property
    def is_trained(self) -> bool:
        return all(idx.is_trained for idx in self.parts().values())

    def train(self, float_codes: np.ndarray | None, binary_codes: np.ndarray | None) -> None:
        """Train the parts whose kind needs it (IVF's quantizer) on codes of the fitting photos."""
        for idx, codes in ((self.float, float_codes), (self.binary, binary_codes)):
            if idx is not None and not idx.is_trained:
                idx.train(codes)

    def save_trained(self, directory: Path) -> list[str]:
        """Write the trained, empty parts that training changed (``index-float.faiss``...) into a fitted
        pipeline's folder; kinds that need no training write nothing. Returns the file names."""
        written = []
        for name, idx in self.parts().items():
            if not build_index(idx.kind, idx.dim, idx.binary).is_trained:
                atomic_write_file(directory / trained_file(name), idx.dump)
                written.append(trained_file(name))
        return written

    def load_trained(self, directory: Path) -> None:
        """Read what ``save_trained`` wrote, for the parts that need it and have it."""
        for name, idx in self.parts().items():
            path = directory / trained_file(name)
            if not idx.is_trained and path.exists():
                idx.load(path)

    # -- changes --------------------------------------------------------------------------------------
    @property
    def holds_positions(self) -> bool:
        """Whether the parts store each reference's position, so a search can keep to a box of positions
        (``search``'s ``box``) instead of a list of ids read from the store (a remote kind: ``milvus``)."""
        parts = list(self.parts().values())
        return bool(parts) and all(idx.holds_positions for idx in parts)

    def add(
        self,
        ids: np.ndarray,
        float_codes: np.ndarray | None,
        binary_codes: np.ndarray | None,
        positions: np.ndarray | None = None,
    ) -> None:
        """``positions``: (n, 2) latitude and longitude of each reference, handed to the parts that hold them
        (``holds_positions``; the others keep none: the store has them)."""
        for idx, codes in ((self.float, float_codes), (self.binary, binary_codes)):
            if idx is None:
                continue
            if idx.holds_positions:
                idx.add(ids, codes, positions)
            else:
                idx.add(ids, codes)

    def remove(self, ids) -> int:
        n = 0
        for idx in self.parts().values():
            n = idx.remove(ids)
        return n

    def compact(self) -> None:
        for idx in self.parts().values():
            idx.compact()

    @property
    def compaction_due(self) -> bool:
        """Whether a part would drop removed vectors now (a snapshot then writes a compacted copy)."""
        return any(idx.compaction_due for idx in self.parts().values())

    @property
    def tombstones(self) -> int:
        """Removed references still stored (``VectorIndex.removed_ids``), until compaction."""
        idx = self._first()
        return len(idx.removed_ids()) if idx is not None else 0

    def copy(self) -> ReferenceIndex:
        twin = object.__new__(ReferenceIndex)
        twin.config = self.config
        twin.serving = self.serving
        twin.float = self.float.copy() if self.float is not None else None
        twin.binary = self.binary.copy() if self.binary is not None else None
        return twin

    def stats(self) -> dict[str, dict[str, Any]]:
        """Each part's kind and parameters (/ready, /metrics)."""
        return {name: idx.stats() for name, idx in self.parts().items()}

    def check_mode(self, mode: str | None) -> str:
        """The mode to use: the configuration's best when None; an error naming the choices otherwise."""
        modes = self.config.modes
        if mode is None:
            return modes[0]
        if mode not in modes:
            raise UnsupportedMode(unsupported_mode_message(mode, self.config, self.serving))
        return mode

    def search(
        self,
        float_code: np.ndarray | None,
        binary_code: np.ndarray | None,
        k: int,
        mode: str | None = None,
        allowed: np.ndarray | None = None,
        box: tuple[float, float, float, float] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One query -> (scores, ids) of up to ``k`` references, best first, scores in [0, 1]. ``allowed``:
        only those ids; ``box`` (min_lon, min_lat, max_lon, max_lat): only references positioned inside it,
        on an index that ``holds_positions``."""
        mode = self.check_mode(mode)
        where: dict[str, Any] = {"allowed": allowed}
        if box is not None:
            if not self.holds_positions:
                raise ValueError("this index holds no positions: filter by the region's ids (allowed)")
            where["box"] = box
        if mode == "float":
            s, i = self.float.search(float_code[None], k, **where)
        elif mode == "binary":
            s, i = self.binary.search(binary_code[None], k, **where)
        else:
            shortlist = max(self.config.shortlist, k)
            _, cand = self.binary.search(binary_code[None], shortlist, **where)
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

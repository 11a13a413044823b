"""The vector-index seam: what every index kind provides (``VectorIndex``) and the registry that builds one.

Why a protocol and a registry: the collection, its snapshots, the SVM bank's training, /ready and /metrics
used to reach into one FAISS class (its ``_index``, ``ntotal``, serialised bytes), so a new kind (an
IVF-PQ index for 10^7 references, a remote vector engine) touched about 8 files. Now a kind is one module
that calls ``register_index_kind`` plus a named configuration that names it (``float_index`` /
``binary_index``); everything else builds indexes through ``build_index`` and uses only this protocol.

A kind that is not registered yet is looked up by module name in ``app.engine.index.kinds`` (``ivf-pq``
-> ``app/engine/index/kinds/ivf_pq.py``), as hloc finds its extractors: no central list of kinds to edit.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from app.engine.errors import GeolocError

#: Where built-in and plug-in kinds live, one module per kind.
KINDS_PACKAGE = "app.engine.index.kinds"


class UnknownIndexKind(GeolocError):
    pass


class IndexNotTrained(GeolocError):
    """A kind that needs training (IVF's coarse quantizer) was given vectors before ``train``."""


@runtime_checkable
class VectorIndex(Protocol):
    """One index of float (inner product) or binary (Hamming) codes, with stable int64 ids.

    Scores are in [0, 1] whatever the kind (cosine mapped to (1 + cos) / 2; 1 - Hamming / bits), so that
    callers threshold one way in every mode. ``add`` and ``remove`` are live and cost the same whatever the
    collection's size (a kind may keep removals as tombstones that searches skip until ``compact``)."""

    kind: str  # the registered kind's name
    dim: int  # float dimension, or bits for binary codes
    binary: bool
    #: True for a kind that stores each reference's position beside its codes: its ``add`` takes
    #: ``positions`` and its ``search`` a ``box`` (``ReferenceIndex.holds_positions``).
    holds_positions: bool

    @property
    def is_trained(self) -> bool:
        """True for kinds that need no training, and for trained ones."""
        ...

    def train(self, x: np.ndarray) -> None:
        """The explicit training step (at fit and refit, on the fitting photos' codes); a no-op for kinds
        that need none."""
        ...

    def add(self, ids: np.ndarray, x: np.ndarray) -> None: ...

    def remove(self, ids) -> int:
        """Returns how many of ``ids`` were stored and are now removed."""
        ...

    def compact(self) -> None:
        """Drop removed vectors for good (on a copy, off the request path: when a snapshot is written)."""
        ...

    def removed_ids(self) -> np.ndarray:
        """Ids removed but still stored (tombstones): a snapshot records them beside the file, and ``load``
        followed by ``remove`` of them gives the same index back."""
        ...

    def search(self, q: np.ndarray, k: int, allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(nq, k) scores best first and ids, -1 padded; ``allowed`` restricts the search itself to those
        ids (the region filter)."""
        ...

    def score_ids(self, q: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """Exact scores of one query against stored ``ids`` (the re-rank of a two-stage search)."""
        ...

    def ids(self) -> np.ndarray:
        """The live ids."""
        ...

    @property
    def size(self) -> int:
        """Live vectors (removed ones excluded)."""
        ...

    def copy(self) -> VectorIndex:
        """An independent copy (a snapshot is compacted and written from one, with the lock released)."""
        ...

    def dump(self, path: Path) -> None:
        """Write the index to one file, streamed (no second copy in memory at 10^7 references)."""
        ...

    def stage_dump(self, path: Path) -> StagedDump:
        """Begin ``dump`` into ``path`` (a new file) from this very index, without a copy of it: what must be
        read while nothing changes the index is written now (the caller holds its lock), the rest by the
        returned ``StagedDump`` afterwards, without the lock."""
        ...

    @property
    def compaction_due(self) -> bool:
        """Whether ``compact`` would drop something now (a snapshot then writes a compacted copy)."""
        ...

    def load(self, path: Path) -> None:
        """Replace this index by the one ``dump`` wrote (trained state included; no removals)."""
        ...

    def stats(self) -> dict[str, Any]:
        """The kind and its parameters (nlist, nprobe, code bytes, ...), for /ready and /metrics."""
        ...


@dataclass(frozen=True)
class StagedDump:
    """The rest of a ``stage_dump``: ``finish()`` writes it without the index's lock (and closes the file);
    ``adopt(final_path)``, called under the lock once the file is in place and only if the index is still
    the one served, lets the index read from that file (the float code table of ``ivf-rabitq``)."""

    finish: Callable[[], None] = lambda: None
    adopt: Callable[[Path], None] = lambda path: None


#: ``factory(dim, binary, **params)`` -> a ``VectorIndex``.
IndexFactory = Callable[..., VectorIndex]

_KINDS: dict[str, IndexFactory] = {}


def checked_codes(x: np.ndarray, dim: int, binary: bool) -> np.ndarray:
    """Codes as every kind takes them: 2-D, contiguous, uint8 bytes (binary) or float32, of the index's
    dimension (a wrong one is refused here rather than by the engine, whose message names nothing of ours)."""
    x = np.atleast_2d(x)
    if binary:
        x = np.ascontiguousarray(x, dtype=np.uint8)
        if x.shape[1] * 8 != dim:
            raise ValueError(f"binary codes of {x.shape[1] * 8} bits for an index of {dim}")
    else:
        x = np.ascontiguousarray(x, dtype=np.float32)
        if x.shape[1] != dim:
            raise ValueError(f"vectors of dimension {x.shape[1]} for an index of {dim}")
    return x


def register_index_kind(name: str, factory: IndexFactory) -> None:
    """Called by the kind's own module when it is imported."""
    _KINDS[name] = factory


def _module_name(kind: str) -> str:
    return f"{KINDS_PACKAGE}.{kind.replace('-', '_')}"


def _factory(kind: str) -> IndexFactory:
    if kind not in _KINDS:
        try:
            importlib.import_module(_module_name(kind))
        except ModuleNotFoundError as e:
            if e.name != _module_name(kind):  # the kind's module exists but lacks a dependency: say that
                raise
    try:
        return _KINDS[kind]
    except KeyError:
        raise UnknownIndexKind(f"unknown index kind {kind!r}; choose one of {', '.join(index_kinds())}") from None


def build_index(kind: str, dim: int, binary: bool, **params: Any) -> VectorIndex:
    """The one factory: every index of the service (live, snapshot, SVM training, evaluation) is built here."""
    return _factory(kind)(dim, binary, **params)


def index_kinds() -> list[str]:
    """The registered kinds and those a module in ``app.engine.index.kinds`` provides."""
    package = importlib.import_module(KINDS_PACKAGE)
    shipped = {m.name.replace("_", "-") for m in pkgutil.iter_modules(package.__path__)}
    return sorted(shipped | set(_KINDS))

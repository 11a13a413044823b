"""When the index changes shape: how often a snapshot is written (``SnapshotPolicy``) and when an exact
index gives way to the compressed kinds (``IndexSizing``). Plain values with their rule, made from
``Settings`` at each entry point and passed to the collection. Light to import (``Settings`` imports it,
and every command reads its settings): the index module, and FAISS with it, is loaded only to describe a
kind."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from app.engine.index.references import ReferenceIndex


@dataclass(frozen=True)
class SnapshotPolicy:
    """Write a snapshot after ``every_changes`` index changes, or ``every_seconds`` after the first change
    not yet in one, and at a clean shutdown. A restart then replays at most that many changes."""

    every_changes: int = 5_000
    every_seconds: float = 300.0

    def due(self, pending_changes: int, seconds_pending: float) -> bool:
        """``seconds_pending``: since the oldest change not yet in a snapshot."""
        return pending_changes >= self.every_changes or (pending_changes > 0 and seconds_pending >= self.every_seconds)


@dataclass(frozen=True)
class SharedIndex:
    """The index on a server every replica shares (the ``milvus`` kind, ``GEOLOC_MILVUS_URI``) instead of in
    each process: no per-replica build from the change log and no snapshot; the process holding the writer
    role alone writes to it, and records in the store the change-log version it holds, so that the others
    know how far it is. ``collection``: the base name of its collections (one per part and generation).
    ``wait_seconds``: how long a search waits for the writer to apply changes the store already holds (a
    finished upload is found first through every replica); past it, it searches what the server has."""

    uri: str
    collection: str = "geoloc"
    kind: str = "milvus"
    wait_seconds: float = 10.0

    def params(self, part: str, generation: int) -> dict:
        """``build_index`` keyword arguments of one part of one generation (a re-fit's codes get new ones)."""
        from app.engine.index.kinds.milvus import collection_name

        return {"uri": self.uri, "collection": collection_name(self.collection, part, generation)}

    def version_key(self, generation: int) -> str:
        """The store's meta key holding the change-log version the server's collections hold; it names their
        layout, so collections an earlier layout filled count as never filled (the writer fills them again)."""
        from app.engine.index.kinds.milvus import SCHEMA

        return f"shared_index_version:{self.kind}:{self.collection}:g{generation}:{SCHEMA}"


#: ``IndexSizing.switch_at``'s default (``Settings.index_switch_at``).
DEFAULT_SWITCH_AT = 200_000


@dataclass(frozen=True)
class IndexSizing:
    """When the exact index gives way to the compressed kinds: at ``switch_at`` live
    references (0: never), for a configuration whose kinds are exact and that lets the size choose
    (``PipelineConfig.index_by_size``). The switch goes one way: a collection that shrinks again keeps the
    compressed kind (no back-and-forth around the threshold, and no second training).

    Why 200,000 by default (docs/benchmarks.md, one FAISS thread): the exact float search's time grows in
    proportion to the size, and /locate may take at most 1.2x its time at 10^4 references; the exact search
    uses up that margin near 2 x 10^5 references (and 200 MB of index at 1,032 B each). Below it the exact
    search costs no accuracy and no training; above it the compressed kind searches in a small fraction of
    that time and holds 114 B per reference in RAM (``ivf-rabitq``; its float codes for the re-rank are read
    by ``pread`` from the snapshot file, spilled to a temporary file until the first one)."""

    switch_at: int = DEFAULT_SWITCH_AT
    #: After a failed switch, the next try waits this long (a training that fails fails again at once).
    retry_seconds: float = 600.0
    #: The index on a shared server instead (``SharedIndex``): its kind at every size, nothing switches.
    shared: SharedIndex | None = None

    def due(self, index: ReferenceIndex) -> bool:
        if self.shared is not None:
            return False
        return self.switch_at > 0 and index.switches_by_size and index.is_exact and index.size >= self.switch_at

    def describe(self, index: ReferenceIndex, switching: bool) -> str:
        """How the kind is chosen, for /ready."""
        from app.engine.index.references import COMPRESSED_KINDS

        if self.shared is not None:
            from app.engine.index.kinds.milvus import public_uri

            return (
                f"{self.shared.kind} at every size: the collections {self.shared.collection}_* on "
                f"{public_uri(self.shared.uri)}, shared by every replica"
            )
        if not index.switches_by_size:
            return "the configuration's kinds at every size"
        if self.switch_at <= 0:
            return "exact at every size (GEOLOC_INDEX_SWITCH_AT=0)"
        compressed = " / ".join(COMPRESSED_KINDS[p] for p in index.parts())
        if not index.is_exact:
            return f"{compressed}: switched from exact at {self.switch_at} references"
        now = "; switching now (built in the background, the exact index serves meanwhile)" if switching else ""
        return f"exact below {self.switch_at} references, then {compressed}{now}"

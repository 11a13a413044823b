"""The collection as one process sees it: the store, the fitted pipeline, and a live index kept current.

Why it is built this way (cost per change independent of the collection's size):
- The index is loaded once (a verified snapshot plus the change log after it, or, when no snapshot can be
  trusted, a full rebuild from the codes in SQLite) and then only *caught up*: before each search the
  process compares the log's last version with the one it holds (one indexed SQL read) and applies exactly
  the changes in between, adds in place and deletions as tombstones.
- The index's kind follows the collection's size (``IndexSizing``): exact (flat) while small, the
  compressed kinds (``ivf-rabitq`` / ``binary-ivf``) once it reaches ``switch_at`` references. The switch is
  made as a new generation is loaded: trained on a sample of the collection's own codes and filled from the
  store in the background while the exact index serves, then swapped in under the lock after replaying
  what arrived meanwhile; the next snapshot records the kind, so a restart comes back with it.
- Snapshots are written by one process only (the one holding the worker lock), in the background, by the
  policy below: on a copy of the index taken under the lock (a memory copy), compacted and written to disk
  with the lock released, then swapped in after replaying what arrived meanwhile. Searches never wait for
  a disk write.
- With a shared index (``IndexSizing.shared``: the ``milvus`` kind) the index lives on a server every
  replica uses: no snapshot and no build per process. The process holding the writer role applies the log
  to it and records in the store the version the server holds; the others read that version and, before a
  search, wait (up to ``SharedIndex.wait_seconds``) until it reaches the store's, so that a finished upload
  is found and a deleted reference is gone through every replica.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.engine.calibration import Calibration
from app.engine.configs import DEFAULT_CONFIG
from app.engine.index.float_code_table import use_spill_dir
from app.engine.index.references import ReferenceIndex
from app.engine.pipeline import Pipeline, PipelineSource
from app.policies import IndexSizing, SnapshotPolicy
from app.runtime import release_free_memory
from app.storage.backend import StorageBackend
from app.storage.changes import Change
from app.storage.generations import CodeChunk
from app.storage.snapshots import SnapshotInvalid, SnapshotMismatch, StagedSnapshot, load_snapshot
from app.storage.store import ReferenceStore

log = logging.getLogger("geoloc.collection")


@dataclass
class IndexStats:
    """What /metrics reports about the index's upkeep in this process."""

    full_rebuilds: int = 0
    replayed_at_start: int = 0
    snapshot_writes: int = 0
    snapshot_version: int | None = None
    snapshot_written_at: float | None = None  # wall time of the snapshot loaded or last written
    changes_applied: int = 0
    kind_switches: int = 0  # exact -> compressed switches by size (``IndexSizing``)


def apply_changes(index: ReferenceIndex, changes: list[Change]) -> None:
    """Apply log entries in order: runs of adds in one call each, deletions as tombstones. An add whose row
    is gone (deleted since; its delete entry is in the same read) is skipped, and so is that delete. A move
    changes nothing in an index that keeps no positions (the store's are read at every search); one that
    holds them is written the reference again, at its position now."""
    skipped: set[int] = set()
    run: list[Change] = []

    def flush() -> None:
        if not run:
            return
        ids = np.array([c.ref_id for c in run], np.int64)
        f = np.stack([np.frombuffer(c.float_code, np.float32) for c in run]) if index.float is not None else None
        b = np.stack([np.frombuffer(c.binary_code, np.uint8) for c in run]) if index.binary is not None else None
        index.add(ids, f, b, np.array([(c.lat, c.lon) for c in run], np.float64))
        run.clear()

    for c in changes:
        if c.op == "move":
            if index.holds_positions and not (c.float_code is None and c.binary_code is None):
                run.append(c)
            continue
        if c.op == "add":
            if c.float_code is None and c.binary_code is None:
                skipped.add(c.ref_id)
            else:
                run.append(c)
        else:
            flush()
            if c.ref_id not in skipped:
                index.remove([c.ref_id])
    flush()


def index_from_stream(
    pipeline: Pipeline, chunks: Iterable[CodeChunk], into: ReferenceIndex | None = None
) -> ReferenceIndex:
    """A new index of ``pipeline``'s kinds (or ``into``, empty and trained) holding the streamed codes, added
    chunk by chunk as they are read (``Generations.code_stream``): the reader holds one chunk, the index the
    rest."""
    index = into if into is not None else pipeline.new_index()
    for c in chunks:
        index.add(c.ids, c.float_codes, c.binary_codes, c.positions)
    return index


DEFAULT_PIPELINE = "models:"  # meta ``pipeline`` prefix: the models dir's pipelines/<config>


def pipeline_source(data_dir: Path, models_dir: Path, pipeline_ref: str | None, config: str) -> PipelineSource:
    """Where the data dir's recorded pipeline is: the models dir's (``models:<config>``, or nothing recorded
    yet) or a re-fitted one in the data dir (``pipelines/<config>-g<N>``)."""
    if not pipeline_ref or pipeline_ref.startswith(DEFAULT_PIPELINE):
        name = pipeline_ref[len(DEFAULT_PIPELINE) :] if pipeline_ref else config
        return PipelineSource.default(Path(models_dir), name or config)
    return PipelineSource(Path(models_dir), Path(data_dir) / pipeline_ref, config)


@dataclass(frozen=True)
class View:
    """One generation's pipeline and index, taken together for one request (``Searchable``)."""

    collection: Collection
    pipeline: Pipeline
    index: ReferenceIndex
    generation: int

    def check_mode(self, mode: str | None) -> str:
        return self.index.check_mode(mode)

    @property
    def holds_positions(self) -> bool:
        return self.index.holds_positions

    def search(self, float_code, binary_code, k: int, mode: str | None = None, allowed=None, box=None):
        with self.collection.lock:
            return self.index.search(float_code, binary_code, k, mode, allowed, box)


class Collection:
    """One per process and data dir. ``search`` and every change of ``index`` hold ``lock``."""

    def __init__(
        self,
        store: ReferenceStore,
        pipeline: Pipeline,
        policy: SnapshotPolicy | None = None,
        generation: int = 0,
        models_dir: Path | None = None,
        sizing: IndexSizing | None = None,
    ):
        self.store = store
        self.pipeline = pipeline
        self.generation = generation
        self.models_dir = models_dir  # where a new generation's ONNX models are loaded from
        self.policy = policy or SnapshotPolicy()
        self.sizing = sizing or IndexSizing()
        self.lock = threading.RLock()
        self.stats = IndexStats()
        self._snapshot_lock = threading.Lock()
        self._reload_lock = threading.Lock()
        self._reloader: threading.Thread | None = None
        self.reload_error: str | None = None  # why the last attempt to load a newer generation failed
        self._switch_lock = threading.Lock()
        self._switcher: threading.Thread | None = None
        self.switch_error: str | None = None  # why the last switch to the compressed kind failed
        self.switch_progress: str | None = None  # what the switch under way is doing (/ready while a start waits)
        self.last_switch: str | None = None  # what the last switch to the compressed kind did, in words
        self._switch_failed_at: float | None = None
        self._first_pending_at: float | None = None  # when the oldest change not in a snapshot was applied
        self.rebuilt = False  # loaded by a full rebuild: a snapshot is due as soon as a writer can take it
        self._calibration: tuple[tuple[int, int], Calibration] | None = None  # (pipeline, version) -> the rule
        self.shared = self.sizing.shared  # the index on a shared server (``SharedIndex``), or None
        self.writes_shared = False  # this process holds the writer role: it alone writes to a shared index
        self.index, self.version = self._load()

    @classmethod
    def open(
        cls,
        data_dir: Path,
        models_dir: Path,
        config: str | None,
        policy: SnapshotPolicy | None = None,
        backend: StorageBackend | None = None,
        sizing: IndexSizing | None = None,
    ):
        """The data dir's own configuration and pipeline win over ``config``: its codes were made by them.
        ``backend``: the storage backend the process made once from its Settings (None: from the environment)."""
        store = ReferenceStore(data_dir, backend=backend)
        use_spill_dir(store.data_dir)  # the ivf-rabitq kind's new float codes: on the data dir's disk
        for _ in range(3):  # a re-fit switching between the read and the load: read again
            generation, ref, name = store.generation_state()
            name = name or config or DEFAULT_CONFIG
            pipeline = pipeline_source(data_dir, models_dir, ref, name).load()
            if store.generation_state()[0] == generation:
                break
        store.bind(pipeline)
        if ref is None and not store.read_only:
            store.set_meta("pipeline", DEFAULT_PIPELINE + name)
        return cls(store, pipeline, policy, generation, Path(models_dir), sizing)

    def view(self) -> View:
        """The current generation's pipeline and index, for one request."""
        with self.lock:
            return View(self, self.pipeline, self.index, self.generation)

    # -- loading --------------------------------------------------------------------------------------
    def _load(self) -> tuple[ReferenceIndex, int]:
        if self.shared is not None:
            index = self._shared_index(self.pipeline, self.generation)
            version, ts = self._shared_state(self.generation)
            self._read_shared_at(index, ts)
            return index, version or 0
        try:
            index, manifest = load_snapshot(
                self.store.snapshots_dir, self.pipeline, self.store, new_index=self.pipeline.new_index
            )
        except SnapshotInvalid as e:
            if (self.store.snapshots_dir / "index.json").exists():
                log.warning("snapshot not used (%s): rebuilding the index from the codes in SQLite", e)
            if isinstance(e, SnapshotMismatch):
                self.store.retire_snapshot(e.manifest.version, e.manifest.ref_high_water)
            return self._rebuild()
        version = manifest.version
        changes = self.store.changes_since(version)
        apply_changes(index, changes)
        self.stats.replayed_at_start = len(changes)
        self.stats.snapshot_version = version
        self.stats.snapshot_written_at = float(manifest.written_at or 0) or None
        log.info("index loaded from the snapshot of version %d and %d later changes", version, len(changes))
        return index, changes[-1].version if changes else version

    def _rebuild(self) -> tuple[ReferenceIndex, int]:
        t0 = time.perf_counter()
        with self.store.code_stream() as stream:
            index, version = index_from_stream(self.pipeline, stream.chunks), stream.version
        self.stats.full_rebuilds += 1
        self.rebuilt = True
        release_free_memory()  # what the stream's chunks left in the allocator's arenas
        log.info("index rebuilt from %d stored codes in %.1f s", index.size, time.perf_counter() - t0)
        return index, version

    # -- a shared index (``SharedIndex``) ---------------------------------------------------------------
    def _shared_index(self, pipeline: Pipeline, generation: int) -> ReferenceIndex:
        """The generation's index on the shared server (connected on first use)."""
        shared = self.shared
        assert shared is not None
        parts = [p for p, n in (("float", pipeline.float_dim), ("binary", pipeline.bits)) if n]
        return pipeline.new_index(
            kinds={p: shared.kind for p in parts}, params={p: shared.params(p, generation) for p in parts}
        )

    def _shared_version(self, generation: int) -> int | None:
        """The change-log version the server holds for ``generation`` (None: never filled)."""
        return self._shared_state(generation)[0]

    def _shared_state(self, generation: int) -> tuple[int | None, int | None]:
        """(the version the server holds for ``generation``, the server timestamp the writer took after
        applying it: reads guaranteed at it see every change up to that version). One value ``V@TS``, so a
        reader never pairs a new version with an older timestamp; ``V`` alone (recorded before timestamps):
        no timestamp, reads strongly consistent."""
        assert self.shared is not None
        value = self.store.get_meta(self.shared.version_key(generation))
        if value is None:
            return None, None
        version, _, ts = value.partition("@")
        return int(version), int(ts) if ts else None

    def _record_shared(self, index: ReferenceIndex, generation: int, version: int) -> None:
        """As the writer, after applying changes up to ``version``: record it with a timestamp taken now,
        and read at that timestamp ourselves."""
        assert self.shared is not None
        parts = list(index.parts().values())
        ts = parts[0].fence()
        self.store.set_meta(self.shared.version_key(generation), f"{version}@{ts}")
        for part in parts:
            part.read_after(ts)

    def _read_shared_at(self, index: ReferenceIndex, ts: int | None) -> None:
        for part in index.parts().values():
            part.read_after(ts)

    def hold_writer_role(self, held: bool) -> None:
        """Called by the writer role (``app.ingestion.writer``) as it is taken and given up: only its holder
        writes to a shared index (its next catch-up fills or updates it)."""
        self.writes_shared = held

    def _fill_shared(self, index: ReferenceIndex, generation: int) -> int | None:
        """As the writer: the generation's collections emptied and filled from the store's codes, then their
        version recorded. None when the generation changed meanwhile."""
        assert self.shared is not None
        for part in index.parts().values():
            part.drop()
        with self.store.code_stream() as stream:
            if stream.generation != generation:
                return None
            index_from_stream(self.pipeline, stream.chunks, into=index)
            version = stream.version
        for part in index.parts().values():
            part.connect_fresh()  # made again by this fill: not lost
        self._record_shared(index, generation, version)
        self.stats.full_rebuilds += 1
        log.info("shared index filled with %d references at version %d", index.size, version)
        return version

    def _writer_catch_up(self, head: int) -> int:
        """As the writer (under the lock): fill the server's collections if they were never filled or are gone
        (a new server), then apply the log up to ``head`` and record the version they hold."""
        assert self.shared is not None
        recorded = self._shared_version(self.generation)
        fresh = [p.connect_fresh() for p in self.index.parts().values()]  # every part: each may be lost
        if recorded is None or any(fresh):
            filled = self._fill_shared(self.index, self.generation)
            if filled is None:
                return 0
            self.version = filled
        else:
            self.version = recorded
        changes = [c for c in self.store.changes_since(self.version) if c.version <= head]
        if not changes:
            return 0
        apply_changes(self.index, changes)
        self.version = changes[-1].version
        self._record_shared(self.index, self.generation, self.version)
        self.stats.changes_applied += len(changes)
        return len(changes)

    def _wait_for_shared(self, head: int) -> None:
        """As a reader: wait until the writer has applied the log up to ``head`` (bounded)."""
        assert self.shared is not None
        deadline = time.monotonic() + self.shared.wait_seconds
        while True:
            held, ts = self._shared_state(self.generation)
            held = held or 0
            if held >= head:
                self.version = max(self.version, held)
                self._read_shared_at(self.index, ts)
                return
            if time.monotonic() >= deadline:
                log.warning(
                    "the shared index holds version %d, the store %d: no writer applied the rest within %.0f s",
                    held,
                    head,
                    self.shared.wait_seconds,
                )
                self.version = max(self.version, held)
                self._read_shared_at(self.index, ts)
                return
            time.sleep(0.02)

    # -- switching generation -------------------------------------------------------------------------
    def _load_generation(self) -> bool:
        """Load the data dir's current generation (pipeline, then its snapshot or a rebuild from SQLite)
        without the lock, then swap pipeline, index and version together. True when it swapped."""
        if self.models_dir is None:
            raise RuntimeError("this collection was not opened from a models dir: it cannot load a new generation")
        generation, ref, name = self.store.generation_state()
        if generation == self.generation:
            return False
        t0 = time.perf_counter()
        pipeline = pipeline_source(self.store.data_dir, self.models_dir, ref, name or self.pipeline.config.name).load()
        if self.shared is not None:
            return self._switch_shared_generation(pipeline, generation, ref, t0)
        try:
            index, manifest = load_snapshot(
                self.store.snapshots_dir, pipeline, self.store, new_index=pipeline.new_index
            )
            if manifest.generation != generation:
                raise SnapshotInvalid("the snapshot is of another generation")
            version, rebuilt = manifest.version, False
        except SnapshotInvalid as e:
            if isinstance(e, SnapshotMismatch):
                log.warning("snapshot not used (%s)", e)
                self.store.retire_snapshot(e.manifest.version, e.manifest.ref_high_water)
            with self.store.code_stream() as stream:
                if stream.generation != generation:  # switched again while we loaded: the next catch-up loads it
                    return False
                index, version, rebuilt = index_from_stream(pipeline, stream.chunks), stream.version, True
        with self.lock:
            if self.generation >= generation:
                return False
            self.pipeline, self.index, self.version, self.generation = pipeline, index, version, generation
            self.rebuilt = rebuilt
            self.stats.snapshot_version = None if rebuilt else version
            if rebuilt:
                self.stats.full_rebuilds += 1
        release_free_memory()  # the old generation's index and the stream's chunks
        log.info("switched to generation %d (%s) in %.1f s", generation, ref, time.perf_counter() - t0)
        self.catch_up()
        return True

    def _switch_shared_generation(self, pipeline: Pipeline, generation: int, ref, t0: float) -> bool:
        """``_load_generation`` with a shared index: the writer fills the new generation's collections, the
        others wait for that (they keep serving the old one; the next catch-up tries again)."""
        index = self._shared_index(pipeline, generation)
        version = self._shared_version(generation)
        if version is None:
            if not self.writes_shared:
                return False
            for part in index.parts().values():
                part.drop()
            with self.store.code_stream() as stream:
                if stream.generation != generation:
                    return False
                index_from_stream(pipeline, stream.chunks, into=index)
                version = stream.version
            for part in index.parts().values():
                part.connect_fresh()  # made by this fill: not lost
            self._record_shared(index, generation, version)
        else:
            self._read_shared_at(index, self._shared_state(generation)[1])
        with self.lock:
            if self.generation >= generation:
                return False
            self.pipeline, self.index, self.version, self.generation = pipeline, index, version, generation
        log.info("switched to generation %d (%s) in %.1f s", generation, ref, time.perf_counter() - t0)
        self.catch_up()
        return True

    def _reload_loop(self) -> None:
        try:
            self._load_generation()
            self.reload_error = None
        except Exception as e:  # keep answering from the generation we hold; the next catch-up tries again
            log.exception("loading the new generation failed")
            self.reload_error = str(e)

    def refresh_generation(self, wait: bool = False, timeout: float = 600.0) -> None:
        """Start loading the data dir's newer generation in the background (one loader at a time); ``wait``:
        return once it is loaded (the ingestion worker, which must not encode with a stale pipeline)."""
        with self._reload_lock:
            if self._reloader is None or not self._reloader.is_alive():
                self._reloader = threading.Thread(target=self._reload_loop, name="geoloc-generation", daemon=True)
                self._reloader.start()
            thread = self._reloader
        if wait:
            thread.join(timeout)

    # -- switching kind by size -----------------------------------------------------------------------
    @property
    def switching(self) -> bool:
        """Whether a compressed index is being built in the background now."""
        return self._switcher is not None and self._switcher.is_alive()

    def index_choice(self) -> str:
        """How this collection's index kind is chosen (/ready)."""
        return self.sizing.describe(self.index, self.switching)

    def _start_switch_if_due(self) -> bool:
        """Start ``switch_index_kind`` in the background when the size calls for it (one size comparison: it
        runs at every catch-up). Returns whether a switch is under way (started now or before)."""
        if not self.sizing.due(self.index):
            return self.switching
        failed = self._switch_failed_at
        if failed is not None and time.monotonic() - failed < self.sizing.retry_seconds:
            return self.switching
        with self._switch_lock:
            if not self.switching:
                self.switch_progress = f"building the index {self.index.size:,} references call for"
                self._switcher = threading.Thread(target=self._switch_loop, name="geoloc-index-switch", daemon=True)
                self._switcher.start()
            return True

    def _switch_loop(self) -> None:
        try:
            self.switch_index_kind()
            self.switch_error, self._switch_failed_at = None, None
        except Exception as e:  # keep serving the exact index; try again after ``retry_seconds``
            log.exception("switching the index to the compressed kind failed")
            self.switch_error, self._switch_failed_at = str(e), time.monotonic()
        finally:
            self.switch_progress = None

    def index_at_size(
        self, report: Callable[[str], None], poll_seconds: float = 1.0, stop: threading.Event | None = None
    ) -> bool:
        """Make the index the kind its size calls for before going on: where the switch is due (a start on
        a data dir a bulk load or a restore left exact above the threshold; the end of a bulk ingest), run it
        now (the same background switch) and wait, handing ``report`` each new line of what it is doing.
        Returns whether the index is the size's kind; False where the switch failed (the exact index then
        serves, and the switch is tried again later as at any size) or ``stop`` was set meanwhile."""
        self._apply_logged()
        if self._start_switch_if_due():  # said here at once: a small switch may be over by the first poll
            said = self.switch_progress or f"building the index {self.index.size:,} references call for"
            report(said)
        else:
            said = None
        while self.switching and not (stop is not None and stop.is_set()):
            line = self.switch_progress or said
            if line != said:
                report(line)
                said = line
            self._switcher.join(poll_seconds)
        return not self.sizing.due(self.index)

    def switch_index_kind(self) -> bool:
        """Replace the exact index by the compressed kinds, as a new generation is loaded: a training sample
        read from the exact index under the lock, then without it the compressed kinds trained on it and
        filled from the store's code stream (the exact index serves meanwhile), then under the lock the
        changes logged since the stream's version replayed and the new index swapped in. Returns whether it
        swapped (False: not due, or a new generation came meanwhile)."""
        t0 = time.perf_counter()
        with self.lock:
            exact, generation = self.index, self.generation
            if not self.sizing.due(exact):
                return False
            size = exact.size
            sample = exact.sample(ReferenceIndex.sample_size(size))
        trained_on = max(len(codes) for codes in sample if codes is not None)
        self.switch_progress = f"building the index {size:,} references call for: training on {trained_on:,} codes"
        compressed = exact.compressed(size, *sample)
        del sample
        trained_s = time.perf_counter() - t0
        with self.store.code_stream() as stream:
            if stream.generation != generation:
                return False
            chunks = self._counted(stream.chunks, size, trained_s)
            compressed, built_at = index_from_stream(self.pipeline, chunks, into=compressed), stream.version
        with self.lock:
            if self.generation != generation:
                return False
            if built_at < self.version:
                apply_changes(compressed, [c for c in self.store.changes_since(built_at) if c.version <= self.version])
            self.index, self.version = compressed, max(self.version, built_at)
            self.rebuilt = True  # a snapshot of the new kind is due at once: a restart comes back with it
            built_s = time.perf_counter() - t0 - trained_s
            self.last_switch = (
                f"index switched to {', '.join(f'{part} {kind}' for part, kind in compressed.kinds().items())} "
                f"at {compressed.size:,} references "
                f"(trained in {trained_s:.1f} s, built in {built_s:.1f} s)"
            )
            self.stats.kind_switches += 1
        del exact
        release_free_memory()  # the exact index's codes, the stream's chunks
        log.info(self.last_switch)
        return True

    def _counted(self, chunks: Iterable[CodeChunk], size: int, trained_s: float) -> Iterator[CodeChunk]:
        """The stream's chunks, each counted into ``switch_progress`` as it is added."""
        added = 0
        for c in chunks:
            yield c
            added += len(c.ids)
            self.switch_progress = (
                f"building the index {size:,} references call for: trained in {trained_s:.0f} s, "
                f"{added:,} of {size:,} references added"
            )

    # -- keeping current ------------------------------------------------------------------------------
    def catch_up(self) -> int:
        """Apply the changes other processes (or this one's worker) logged since our version; returns how many.
        One read gives the version and the generation; a newer generation is loaded in the background and,
        until it is swapped in, the old index takes no change (those logged after the switch are the new
        generation's codes). The size this leaves may start the switch to the compressed kinds."""
        applied = self._apply_logged()
        self._start_switch_if_due()
        return applied

    def _apply_logged(self) -> int:
        version, generation = self.store.head()
        if generation != self.generation:
            self.refresh_generation()
            return 0
        if self.shared is not None:
            if self.writes_shared:
                with self.lock:
                    return self._writer_catch_up(version) if generation == self.generation else 0
            if version > self.version:
                self._wait_for_shared(version)
            return 0
        if version == self.version:
            return 0
        with self.lock:
            if generation != self.generation:
                return 0
            changes = [c for c in self.store.changes_since(self.version) if c.version <= version]
            if not changes:
                return 0
            apply_changes(self.index, changes)
            self.version = changes[-1].version
            self.stats.changes_applied += len(changes)
            if self._first_pending_at is None:
                self._first_pending_at = time.time()
            return len(changes)

    @property
    def size(self) -> int:
        return self.index.size

    def calibration(self, pipeline: Pipeline | None = None) -> Calibration:
        """The rule that judges this collection's answers: ``pipeline``'s calibration when it was fitted on
        this collection (``Calibration.for_collection``), else the conservative rule saying why. Looked up
        again when the pipeline or the collection's version changes (one indexed query of at most 600
        hashes)."""
        pipeline = pipeline or self.pipeline
        cal = pipeline.calibration
        if not cal.calibrated or not cal.references:
            return cal.for_collection(0)
        key = (id(pipeline), self.version)
        cached = self._calibration
        if cached is not None and cached[0] == key:
            return cached[1]
        judged = cal.for_collection(len(self.store.existing_ids(cal.references)))
        self._calibration = (key, judged)
        return judged

    def calibration_summary(self) -> str:
        """``calibration``'s note, and what the collection needs when no answer of it can be confident yet
        (/ready, so that a small collection's answers are not taken for a fault)."""
        cal = self.calibration()
        needs = cal.confidence_note(self.size)
        return cal.note + (f"; {needs}" if needs else "")

    def check_mode(self, mode: str | None) -> str:
        return self.index.check_mode(mode)

    @property
    def holds_positions(self) -> bool:
        return self.index.holds_positions

    def search(self, float_code, binary_code, k: int, mode: str | None = None, allowed=None, box=None):
        """``ReferenceIndex.search`` on the current index (caught up first, and safe against changes)."""
        self.catch_up()
        with self.lock:
            return self.index.search(float_code, binary_code, k, mode, allowed, box)

    # -- snapshots (only the process holding the worker lock calls these) ------------------------------
    def pending_changes(self) -> int:
        return self.version - (self.stats.snapshot_version or 0)

    def snapshot_due(self) -> bool:
        if self.shared is not None:  # the server keeps its data: nothing to snapshot
            return False
        if self.rebuilt:
            return True
        pending = self.pending_changes()
        if pending and self._first_pending_at is None:  # replayed at start: count from then
            self._first_pending_at = time.time()
        waited = time.time() - self._first_pending_at if self._first_pending_at is not None else 0.0
        return self.policy.due(pending, waited)

    def write_snapshot(self) -> bool:
        """Write the index as of now. Without a compaction due (always for the IVF kinds), from the served
        index itself, with no copy of it: under the lock what must not change meanwhile is written (FAISS's
        part, streamed to the file; ``StagedSnapshot``), the rest (``ivf-rabitq``'s float codes, the fsync,
        the manifest) without it, then under the lock again the index reads from its new file. With a
        compaction due (tombstones of a flat index), a copy is compacted and written without the lock and
        swapped in after replaying whatever was applied meanwhile. Returns False when there was nothing to
        write."""
        if self.shared is not None:  # only the writer role's holder calls this: it brings the server up to date
            self.writes_shared = True
            self.catch_up()
            return False
        with self._snapshot_lock:
            self.catch_up()
            with self.lock:
                if self.stats.snapshot_version == self.version and not self.rebuilt:
                    return False
                v0, gen0, pipeline, source = self.version, self.generation, self.pipeline, self.index
                if self.store.head()[1] != gen0:  # a re-fit switched: this generation is done with
                    return False
                t0 = time.perf_counter()
                in_place = not source.compaction_due
                if in_place:
                    staged, written = StagedSnapshot(self.store.snapshots_dir, source, v0, gen0), source
                    locked_s = time.perf_counter() - t0
                else:
                    written = source.copy()
            if not in_place:
                written.compact()
                t0 = time.perf_counter()
                if self.store.head()[1] != gen0:  # a re-fit switched meanwhile: this generation is done with
                    return False
                staged, locked_s = StagedSnapshot(self.store.snapshots_dir, written, v0, gen0), 0.0
            manifest = staged.finish(pipeline, self.store.binding(v0))
            with self.lock:
                if self.generation != gen0:  # swapped while we wrote: the new generation's index stays
                    return False
                if self.index is source:  # else the kind switched meanwhile: it stays, due for its snapshot
                    staged.adopt()
                    if not in_place:
                        later = [c for c in self.store.changes_since(v0) if c.version <= self.version]
                        apply_changes(written, later)
                        self.index = written
                    self.rebuilt = False
                size = written.size
                del source, written, staged  # before the trim: the table's lookups and the frozen copy's
            release_free_memory()  # the index replaced by its compacted copy, and the writer's buffers
            self.stats.snapshot_writes += 1
            self.stats.snapshot_version = v0
            self._first_pending_at = time.time() if self.version > v0 else None
            self.stats.snapshot_written_at = manifest.written_at
            log.info(
                "snapshot of version %d written (%d references) %s in %.2f s, %.2f s of it holding the index",
                v0,
                size,
                "in place" if in_place else "from a compacted copy",
                time.perf_counter() - t0,
                locked_s,
            )
            self.store.checkpoint()  # the main file catches up with the snapshot: a copy of it alone matches
            return True


class SnapshotWriter:
    """The background thread that writes snapshots by the policy, and a last one at a clean stop. It also
    checkpoints the database (the WAL's pages into the main file) every ``checkpoint_seconds``, and empties
    the WAL at the stop: the data dir's main file is never far behind what was accepted."""

    def __init__(self, collection: Collection, check_seconds: float = 2.0, checkpoint_seconds: float = 10.0):
        self.collection = collection
        self.check_seconds = check_seconds
        self.checkpoint_seconds = checkpoint_seconds
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._checkpointed_at = time.monotonic()

    def run(self) -> None:
        while not self._stop.wait(self.check_seconds):
            try:
                self.collection.catch_up()
                if self.collection.snapshot_due():
                    self.collection.write_snapshot()
            except Exception:  # a failed write is retried at the next check; the log still holds everything
                log.exception("snapshot write failed")
            if time.monotonic() - self._checkpointed_at >= self.checkpoint_seconds:
                self.collection.store.checkpoint()  # PASSIVE: never waits for a reader nor blocks a writer
                self._checkpointed_at = time.monotonic()

    def start(self) -> None:
        self._thread = threading.Thread(target=self.run, name="geoloc-snapshot", daemon=True)
        self._thread.start()

    def stop(self, final: bool = True) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(60)
        if final:
            try:
                self.collection.write_snapshot()
            except Exception:
                log.exception("final snapshot write failed")
            self.collection.store.checkpoint("TRUNCATE")  # a clean stop leaves every row in the main file

"""The float codes of an ``ivf-rabitq`` index, by id, for the exact re-rank of its shortlist.

Why the kind keeps them itself, in files: the re-rank reads ~100 float codes per query, by id. Reading them
from the reference store would reach from the engine into app/ (the engine imports nothing of it), cost a
database query per search and need a reader in every place an index is made (snapshots, the SVM bank's
training, the evaluation). Holding them in RAM would cost 1 KB per reference, ten times the compressed
codes. So ``dump`` writes them into the index's own file, after FAISS's part, sorted by id, and ``read``
keeps that file open: the ids (8 bytes per reference) and a live mask are the only part in RAM.

Why rows are read with ``os.pread`` and not through a memory map (measured, docs/benchmarks.md): the kernel
maps large page-cache folios, so each code a mapped re-rank read made far more of the file than its row
resident in the process (RssFile grew by hundreds of MB within a few /locates at 10^6 references;
``madvise(MADV_RANDOM)`` did not help). A ``pread`` copies the ~100 rows a query asks for and leaves the
file's pages in the OS's cache (shared, evictable), counted in no process. Runs of nearby rows are read in one
call (a snapshot's sorted copy).

Live changes: codes added since the file was written go to a spill file (an unlinked temporary file in the
folder ``use_spill_dir`` names: the service names its data dir; else the system's ``TMPDIR``), not to the
heap, and are read back the same way; the table keeps
their ids, rows and a live flag (24 bytes each). So an index built from the database (a first start, the
switch from the exact index) never holds the float codes a second time in RAM beside whatever else holds
them. A removed or replaced id is marked dead where it is. A snapshot writes the live codes into a new
file; ``rebase`` then reads from it, keeping what changed while it was written. A snapshot replaces its
file by rename, so the open file this table reads stays valid after the path moves on.
"""

from __future__ import annotations

import os
import struct
import tempfile
import threading
import weakref
from pathlib import Path
from typing import BinaryIO

import numpy as np

#: Rows written per chunk: a snapshot streams, never materialising all codes at once.
CHUNK = 16_384
#: Rows at most this far apart are read in one ``pread`` (16 KB of 256-d codes: cheaper than a call).
GAP = 16
#: Recent entries searched unsorted before the lookup sorts them all again.
RESORT_TAIL = 4096


_spill_dir: Path | None = None


def use_spill_dir(folder: Path | None) -> None:
    """Spill files made from now on go to ``folder`` (None: the system's temporary folder). Why the service
    names its data dir: the switch to ``ivf-rabitq`` spills every code of the collection, 1 KB per reference
    (10 GB at 10^7), and a temporary folder is often small or a tmpfs held in RAM; the data dir's disk holds
    the same codes in the snapshot anyway. A folder that cannot take the file falls back to ``TMPDIR``."""
    global _spill_dir
    _spill_dir = None if folder is None else Path(folder)


class RowFile:
    """float32 rows of one width at ``offset`` of an open file, read by ``pread``; a spill file is also
    appended to (under a lock: the copies a snapshot makes share it). The descriptor closes with the last
    table that uses it."""

    def __init__(self, fd: int, offset: int, dim: int, rows: int = 0):
        self.fd, self.offset, self.dim = fd, offset, dim
        self.row_bytes = 4 * dim
        self.rows = rows
        self._lock = threading.Lock()
        weakref.finalize(self, os.close, fd)

    @classmethod
    def open(cls, path: Path, offset: int, dim: int, rows: int) -> RowFile:
        return cls(os.open(path, os.O_RDONLY), offset, dim, rows)

    @classmethod
    def spill(cls, dim: int) -> RowFile:
        """An unlinked temporary file: on disk (through the page cache), gone with the process."""
        try:
            fd, path = tempfile.mkstemp(prefix=".geoloc-float-codes-", suffix=".spill", dir=_spill_dir)
        except OSError:  # a read-only or vanished data dir: the system's temporary folder still works
            fd, path = tempfile.mkstemp(prefix=".geoloc-float-codes-", suffix=".spill")
        os.unlink(path)
        return cls(fd, 0, dim)

    def append(self, codes: np.ndarray) -> np.ndarray:
        """Write ``codes`` after the last row; their row numbers."""
        data = np.ascontiguousarray(codes, np.float32).tobytes()
        with self._lock:
            start = self.rows
            view, at = memoryview(data), self.offset + start * self.row_bytes
            while view:  # pwrite may write less than asked
                n = os.pwrite(self.fd, view, at)
                view, at = view[n:], at + n
            self.rows += len(codes)
        return np.arange(start, start + len(codes), dtype=np.int64)

    def _pread(self, first: int, count: int) -> np.ndarray:
        size, at = count * self.row_bytes, self.offset + first * self.row_bytes
        data = os.pread(self.fd, size, at)
        while len(data) < size:  # a short read (a signal; a network file system)
            more = os.pread(self.fd, size - len(data), at + len(data))
            if not more:
                raise OSError(f"float codes cut short: row {first + len(data) // self.row_bytes} is past the end")
            data += more
        return np.frombuffer(data, np.float32).reshape(count, self.dim)

    def read(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), dim) codes in the order asked: one ``pread`` per run of rows at most ``GAP`` apart; a
        lone row (the re-rank's usual case) is read straight into its place in the result."""
        rows = np.asarray(rows, np.int64)
        out = np.empty((len(rows), self.dim), np.float32)
        if not len(rows):
            return out
        order = np.argsort(rows, kind="stable")
        ranked = rows[order]
        cuts = np.flatnonzero(np.diff(ranked) > GAP) + 1
        flat, rb = memoryview(out).cast("B"), self.row_bytes
        for lo, hi in zip(np.r_[0, cuts].tolist(), np.r_[cuts, len(ranked)].tolist(), strict=True):
            first = int(ranked[lo])
            if hi - lo == 1:
                at = int(order[lo]) * rb
                if os.preadv(self.fd, [flat[at : at + rb]], self.offset + first * rb) == rb:
                    continue
            block = self._pread(first, int(ranked[hi - 1]) - first + 1)
            out[order[lo:hi]] = block[ranked[lo:hi] - first]
        return out


def _grown(a: np.ndarray, n: int) -> np.ndarray:
    """``a`` with room for at least ``n`` entries (doubling: appends cost O(1) amortised)."""
    if n <= len(a):
        return a
    b = np.zeros(max(n, 2 * len(a), 1024), a.dtype)
    b[: len(a)] = a
    return b


class FloatCodeTable:
    """Float codes by id: an immutable, id-sorted part in the index's file plus the changes since (spilled)."""

    def __init__(self, dim: int):
        self.dim = dim
        self._base: RowFile | None = None
        self._base_ids = np.zeros(0, np.int64)  # sorted
        self._base_live = np.zeros(0, bool)
        # changes since the file: entry i is id _recent_ids[i] at spill row _recent_rows[i]; append-only
        self._spill: RowFile | None = None
        self._recent_ids = np.zeros(0, np.int64)
        self._recent_rows = np.zeros(0, np.int64)
        self._recent_live = np.zeros(0, bool)
        self._n_recent = 0
        # lookup: entries [0, _sorted_upto) by id (``_sorted_ids``, entry numbers ``_sorted_at``); the tail
        # after it is searched linearly until it is worth sorting again
        self._sorted_ids = np.zeros(0, np.int64)
        self._sorted_at = np.zeros(0, np.int64)
        self._sorted_upto = 0

    # -- lookups --------------------------------------------------------------------------------------
    def _base_positions(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not len(self._base_ids):
            return np.zeros(len(ids), np.int64), np.zeros(len(ids), bool)
        pos = np.minimum(np.searchsorted(self._base_ids, ids), len(self._base_ids) - 1)
        return pos, (self._base_ids[pos] == ids) & self._base_live[pos]

    def _recent_entries(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each id its live recent entry (and whether it has one)."""
        n = self._n_recent
        at, found = np.zeros(len(ids), np.int64), np.zeros(len(ids), bool)
        if not n or not len(ids):
            return at, found
        if n - self._sorted_upto > RESORT_TAIL:  # sort again: O(n log n) every RESORT_TAIL entries
            self._sorted_at = np.argsort(self._recent_ids[:n], kind="stable")
            self._sorted_ids = self._recent_ids[:n][self._sorted_at]
            self._sorted_upto = n
        runs = [(self._sorted_ids, self._sorted_at)]
        if n > self._sorted_upto:  # the tail, newer than the sorted part: sorted now, it is small
            tail_at = np.argsort(self._recent_ids[self._sorted_upto : n], kind="stable") + self._sorted_upto
            runs.append((self._recent_ids[tail_at], tail_at))
        for sorted_ids, entry in runs:  # an id's newest entry is the only one that can be live
            if not len(sorted_ids):
                continue
            pos = np.maximum(np.searchsorted(sorted_ids, ids, side="right") - 1, 0)
            cand = entry[pos]
            hit = (sorted_ids[pos] == ids) & self._recent_live[cand]
            at[hit], found[hit] = cand[hit], True
        return at, found

    # -- changes --------------------------------------------------------------------------------------
    def put(self, ids: np.ndarray, codes: np.ndarray) -> None:
        ids = np.asarray(ids, np.int64)
        if not len(ids):
            return
        self.drop(ids)
        if self._spill is None:
            self._spill = RowFile.spill(self.dim)
        rows = self._spill.append(codes)
        n, m = self._n_recent, self._n_recent + len(ids)
        self._recent_ids, self._recent_rows = _grown(self._recent_ids, m), _grown(self._recent_rows, m)
        self._recent_live = _grown(self._recent_live, m)
        self._recent_ids[n:m], self._recent_rows[n:m], self._recent_live[n:m] = ids, rows, True
        self._n_recent = m

    def drop(self, ids: np.ndarray) -> None:
        ids = np.atleast_1d(np.asarray(ids, np.int64))
        pos, found = self._base_positions(ids)
        self._base_live[pos[found]] = False
        at, found = self._recent_entries(ids)
        self._recent_live[at[found]] = False

    # -- reading --------------------------------------------------------------------------------------
    def get(self, ids: np.ndarray) -> np.ndarray:
        """(len(ids), dim) codes in the order asked; KeyError for an id not stored."""
        ids = np.asarray(ids, np.int64)
        out = np.empty((len(ids), self.dim), np.float32)
        pos, in_base = self._base_positions(ids)
        if in_base.any():
            out[in_base] = self._base.read(pos[in_base])
        rest = np.flatnonzero(~in_base)
        if len(rest):
            at, found = self._recent_entries(ids[rest])
            if not found.all():
                raise KeyError(int(ids[rest][~found][0]))
            out[rest] = self._spill.read(self._recent_rows[at])
        return out

    def _recent_live_ids(self, upto: int | None = None) -> np.ndarray:
        n = self._n_recent if upto is None else upto
        return self._recent_ids[:n][self._recent_live[:n]]

    def where(self) -> tuple[int, int]:
        """Live codes read from the index's file, and those in the spill file (changes since it)."""
        return int(self._base_live.sum()), len(self._recent_live_ids())

    def live_ids(self) -> np.ndarray:
        return np.sort(np.concatenate([self._base_ids[self._base_live], self._recent_live_ids()]))

    def copy(self) -> FloatCodeTable:
        """The files are shared (the base is never written; the spill only appended to, each table knowing
        its own rows); the ids and live flags are copied."""
        twin = object.__new__(FloatCodeTable)
        twin.__dict__.update(self.__dict__)
        n = self._n_recent
        twin._base_live = self._base_live.copy()
        twin._recent_ids, twin._recent_rows = self._recent_ids[:n].copy(), self._recent_rows[:n].copy()
        twin._recent_live = self._recent_live[:n].copy()
        return twin

    def rebase(self, written: FloatCodeTable, frozen: FloatCodeTable) -> None:
        """Read from ``written`` (the file a snapshot wrote from ``frozen``, a ``copy`` of this table) from
        now on, keeping the changes made to this table since ``frozen`` was taken: an id still where it was
        then is in the file; one removed or replaced since is dead there, and a replacement or a new id
        is copied into a new spill file (the few changes made while the snapshot was written)."""
        upto = frozen._n_recent
        unchanged = np.concatenate([self._base_ids[self._base_live], self._recent_live_ids(upto)])
        later = np.flatnonzero(self._recent_live[upto : self._n_recent]) + upto
        if len(unchanged) != len(written._base_ids):  # else nothing was removed or replaced meanwhile
            written._base_live &= np.isin(written._base_ids, unchanged)
        if len(later):
            written.put(self._recent_ids[later], self._spill.read(self._recent_rows[later]))
        self.__dict__.update(written.__dict__)

    # -- file part ------------------------------------------------------------------------------------
    _HEAD = struct.Struct("<QQ")  # count, dim

    def write(self, f: BinaryIO) -> None:
        """Append the live codes, sorted by id, to ``f`` (positioned on an 8-byte boundary), in chunks."""
        ids = self.live_ids()
        f.write(self._HEAD.pack(len(ids), self.dim))
        f.write(ids.tobytes())
        for lo in range(0, len(ids), CHUNK):
            f.write(self.get(ids[lo : lo + CHUNK]).tobytes())

    @classmethod
    def read(cls, path: Path, offset: int) -> FloatCodeTable:
        """Open the part ``write`` put at ``offset`` of ``path``: ids read, codes left in the file."""
        with open(path, "rb") as f:
            f.seek(offset)
            n, dim = cls._HEAD.unpack(f.read(cls._HEAD.size))
            ids = np.fromfile(f, np.int64, n)
        if len(ids) != n:
            raise ValueError(f"{path}: the float code table is cut short")
        table = cls(dim)
        if n:
            table._base = RowFile.open(path, offset + cls._HEAD.size + 8 * n, dim, n)
            if os.fstat(table._base.fd).st_size < table._base.offset + n * table._base.row_bytes:
                raise ValueError(f"{path}: the float code table is cut short")
            table._base_ids = ids
            table._base_live = np.ones(n, bool)
        return table

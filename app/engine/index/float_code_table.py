"""The float codes of an ``ivf-rabitq`` index, by id, for the exact re-rank of its shortlist.

Why the kind keeps them itself, in a memory-mapped file: the re-rank reads ~100 float codes per query, by
id. Reading them from the reference store would reach from the engine into app/ (the engine imports
nothing of it), cost a database query per search and need a reader in every place an index is made
(snapshots, the SVM bank's training, the evaluation). Holding them in RAM would cost 1 KB per reference,
ten times the compressed codes. So ``dump`` writes them into the index's own file, after FAISS's part,
sorted by id, and ``load`` maps that region read-only: the pages live in the OS's file cache (shared,
evictable), not in the process's heap, and the ids (8 bytes per reference) are the only copy in RAM.

Live changes: codes added since the file was written are held in RAM (``recent``) until the next snapshot
writes them into a new file, which the snapshotted index then maps (the collection swaps that copy in to
serve); a removed or replaced id is marked dead in the mapped part. A snapshot
replaces its file by rename, so the inode this table maps stays valid after the path moves on.
Known limit: a collection built from the database without a snapshot (a first start, a rebuild) holds
every code in ``recent`` until its first snapshot is written and loaded.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import BinaryIO

import numpy as np

#: Rows written per chunk: a snapshot streams, never materialising all codes at once.
CHUNK = 65_536


class FloatCodeTable:
    """Float codes by id: an immutable, memory-mapped, id-sorted part plus the changes since."""

    def __init__(self, dim: int):
        self.dim = dim
        self._base_ids = np.zeros(0, np.int64)  # sorted
        self._base_codes: np.ndarray = np.zeros((0, dim), np.float32)  # a read-only memmap after ``read``
        self._base_live = np.zeros(0, bool)
        self.recent: dict[int, np.ndarray] = {}

    def _base_positions(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pos = np.searchsorted(self._base_ids, ids)
        pos_ok = np.minimum(pos, max(len(self._base_ids) - 1, 0))
        found = (pos < len(self._base_ids)) & (self._base_ids[pos_ok] == ids) if len(self._base_ids) else pos < 0
        found &= self._base_live[pos_ok] if len(self._base_ids) else found
        return pos_ok, found

    def put(self, ids: np.ndarray, codes: np.ndarray) -> None:
        self.drop(ids)
        for i, code in zip(ids.tolist(), codes, strict=True):
            self.recent[i] = np.array(code, np.float32)

    def drop(self, ids: np.ndarray) -> None:
        pos, found = self._base_positions(np.asarray(ids, np.int64))
        self._base_live[pos[found]] = False
        for i in np.asarray(ids).tolist():
            self.recent.pop(i, None)

    def get(self, ids: np.ndarray) -> np.ndarray:
        """(len(ids), dim) codes in the order asked; KeyError for an id not stored."""
        ids = np.asarray(ids, np.int64)
        out = np.empty((len(ids), self.dim), np.float32)
        pos, found = self._base_positions(ids)
        out[found] = self._base_codes[pos[found]]
        for r in np.flatnonzero(~found):
            out[r] = self.recent[int(ids[r])]
        return out

    def live_ids(self) -> np.ndarray:
        return np.sort(np.concatenate([self._base_ids[self._base_live], np.fromiter(self.recent, np.int64)]))

    def copy(self) -> FloatCodeTable:
        """The mapped part is shared (never written); the live mask and the recent codes are copied."""
        twin = object.__new__(FloatCodeTable)
        twin.__dict__.update(self.__dict__)
        twin._base_live = self._base_live.copy()
        twin.recent = dict(self.recent)
        return twin

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
        """Map the part ``write`` put at ``offset`` of ``path``: ids read, codes mapped read-only."""
        with open(path, "rb") as f:
            f.seek(offset)
            n, dim = cls._HEAD.unpack(f.read(cls._HEAD.size))
            ids = np.fromfile(f, np.int64, n)
        table = cls(dim)
        if n:
            start = offset + cls._HEAD.size + 8 * n
            table._base_ids = ids
            table._base_codes = np.memmap(path, np.float32, "r", offset=start, shape=(n, dim))
            table._base_live = np.ones(n, bool)
        return table

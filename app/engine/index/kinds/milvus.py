"""An index held by a Milvus server (standalone or cluster) instead of this process: one shared index for
every replica, past what one replica's RAM holds.

Why a remote kind: the FAISS kinds keep the whole index in each replica, built from the store's change log.
Past about 10^8 references, or where one shared index is wanted rather than N copies, the index belongs on
a distributed vector engine. Milvus fits the codes: float vectors (inner product, HNSW), binary vectors
(Hamming), scalar fields in filter expressions (the region filter), deletes by primary key, and strong
consistency (a search sees every write acknowledged before it).

One Milvus collection per part (``float`` / ``binary``): an ``id`` primary key, a ``code`` vector and the
reference's position (``lat``, ``lon``), so that a region filter is a range expression the server applies
inside the search, whatever the region holds; an ``id in [...]`` list of the region's references, read from
the store first, grows with the region and has a size cap. Writes are upserts, so replaying a change the
server already holds changes nothing (a new writer replays from the last version it recorded), and a
reference moved is written again with its new position. There is nothing to train, compact or snapshot
here: the server keeps its data. The client connects on first use, so a process starts while Milvus is
down and answers ``IndexUnavailable`` (a 503) until it is back; every call that fails drops the connection
and the next one connects again.

pymilvus is an optional dependency (the ``milvus`` extra): this module imports it only when used.
"""

from __future__ import annotations

import contextlib
import re
import threading
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import numpy as np

from app.engine.errors import GeolocError
from app.engine.index.base import StagedDump, checked_codes, register_index_kind

#: Ids per ``id in [...]`` expression or per upsert: Milvus caps an expression's and a message's size.
BATCH = 4096
#: Seconds one call to the server may take before the index counts as unreachable.
DEFAULT_TIMEOUT = 10.0
#: The most rows one query returns (Milvus's query result window).
MAX_QUERY_ROWS = 16384
#: A filtered search whose filter passes at most this many references scores them all here, exactly, from
#: their codes read in one query: Milvus's HNSW search under a filter that passes few rows (a region of a
#: large collection) misses many of their best matches, whatever its ``ef``. Reading the codes costs time in
#: proportion to their number, hence a bound (docs/milvus.md measures both).
EXACT_FILTERED = 1024
#: The HNSW ``ef`` of a filtered search above ``EXACT_FILTERED`` (a larger region): the graph walk must
#: visit many references the filter rejects before it collects enough that pass, so the unfiltered search's
#: ``ef`` misses many of a large region's best matches, and this one finds them, at a few times the cost
#: (docs/milvus.md measures both, and the regions no ``ef`` helps).
FILTERED_EF = 4096
#: The collections' layout: the meta key recording what a writer filled names it (``SharedIndex``), so a
#: layout change makes the writer fill its collections again from the store, as for a server that lost them.
SCHEMA = "positions"


class IndexUnavailable(GeolocError):
    """The server holding the index cannot be reached or refused the call: retry once it is back (a 503)."""


class SharedIndexNotSnapshotted(GeolocError):
    """A shared index has no snapshot file: the server keeps its data (a bug if ever raised)."""


def public_uri(uri: str) -> str:
    """``uri`` without a password (what /ready, /metrics and error messages show)."""
    parts = urlsplit(uri)
    if parts.password is None:
        return uri
    host = parts.hostname or ""
    netloc = f"{parts.username}:***@{host}" + (f":{parts.port}" if parts.port else "")
    return urlunsplit(parts._replace(netloc=netloc))


def box_expression(box: tuple[float, float, float, float]) -> str:
    """The filter expression of positions inside ``box`` (min_lon, min_lat, max_lon, max_lat), bounds
    included; ``repr`` keeps every digit of a float."""
    min_lon, min_lat, max_lon, max_lat = (float(v) for v in box)
    return f"lat >= {min_lat!r} and lat <= {max_lat!r} and lon >= {min_lon!r} and lon <= {max_lon!r}"


def collection_name(base: str, part: str, generation: int) -> str:
    """The Milvus collection of one part of one generation (a re-fit's codes go into new collections)."""
    name = re.sub(r"[^A-Za-z0-9_]", "_", f"{base}_{part}_g{generation}")
    return name if name[0].isalpha() or name[0] == "_" else f"c_{name}"


class MilvusIndex:
    """A ``VectorIndex`` on one Milvus collection. ``shared``: every process that names the same collection
    sees the same index (the collection layer then lets only the writer write, and writes no snapshot)."""

    kind = "milvus"
    shared = True
    #: Each reference's position is stored beside its codes (``add``'s ``positions``) and a search can keep to
    #: a box of them (``search``'s ``box``).
    holds_positions = True

    def __init__(
        self,
        dim: int,
        binary: bool,
        uri: str = "http://localhost:19530",
        collection: str = "geoloc",
        token: str = "",
        timeout: float = DEFAULT_TIMEOUT,
        m: int = 32,
        ef_construction: int = 200,
        ef_search: int = 256,
        exact_filtered: int = EXACT_FILTERED,
        filtered_ef: int = FILTERED_EF,
    ):
        if binary and dim % 8:
            raise ValueError("binary codes need a multiple of 8 bits")
        self.dim, self.binary = dim, binary
        self.uri, self.collection, self.token, self.timeout = uri, collection, token, timeout
        self.m, self.ef_construction, self.ef_search = m, ef_construction, ef_search
        if not 0 <= exact_filtered <= MAX_QUERY_ROWS:
            raise ValueError(f"exact_filtered must lie in 0..{MAX_QUERY_ROWS} (one query's rows), not {exact_filtered}")
        self.exact_filtered, self.filtered_ef = exact_filtered, filtered_ef
        self.created = False  # this process made the collection (it was absent: new, or the server lost it)
        #: The server timestamp reads are guaranteed at (``read_after``); None: strong consistency.
        self.read_ts: int | None = None
        self._client = None
        self._connect_lock = threading.Lock()

    # -- the connection ---------------------------------------------------------------------------------
    def _call(self, what: str, fn):
        """Run ``fn(client)``; any failure of the server or of the connection is ``IndexUnavailable``, and
        the connection is dropped so that the next call makes a new one."""
        try:
            return fn(self._connected())
        except IndexUnavailable:
            raise
        except Exception as e:  # pymilvus raises MilvusException, grpc errors, timeouts...
            self._client = None
            raise IndexUnavailable(
                f"the Milvus server at {public_uri(self.uri)} cannot {what} ({type(e).__name__}: {e}); "
                "nothing stored is lost: retry once it is reachable"
            ) from e

    def _connected(self):
        client = self._client
        if client is not None:
            return client
        with self._connect_lock:
            if self._client is None:
                from pymilvus import MilvusClient

                client = MilvusClient(uri=self.uri, token=self.token, timeout=self.timeout)
                if not client.has_collection(self.collection, timeout=self.timeout):
                    self._create(client)
                    self.created = True
                client.load_collection(self.collection, timeout=self.timeout)
                self._client = client
            return self._client

    def _create(self, client) -> None:
        from pymilvus import DataType, MilvusClient

        schema = MilvusClient.create_schema(auto_id=False, enable_dynamic_field=False)
        schema.add_field("id", DataType.INT64, is_primary=True)
        schema.add_field("code", DataType.BINARY_VECTOR if self.binary else DataType.FLOAT_VECTOR, dim=self.dim)
        schema.add_field("lat", DataType.DOUBLE)
        schema.add_field("lon", DataType.DOUBLE)
        params = client.prepare_index_params()
        if self.binary:  # the codes are small (32 B at 256 bits): an exact Hamming scan of each segment
            params.add_index(field_name="code", index_type="BIN_FLAT", metric_type="HAMMING")
        else:
            params.add_index(
                field_name="code",
                index_type="HNSW",
                metric_type="IP",
                params={"M": self.m, "efConstruction": self.ef_construction},
            )
        client.create_collection(
            self.collection, schema=schema, index_params=params, consistency_level="Strong", timeout=self.timeout
        )

    def connect_fresh(self) -> bool:
        """Connect now (no call to the server when connected already); True once after this process created
        the collection because the server lacked it (new, or lost): the caller fills it then."""
        self._call("connect", lambda c: None)
        fresh, self.created = self.created, False
        return fresh

    def fence(self) -> int:
        """A timestamp from the server's clock taken after every write this process made was acknowledged:
        a read guaranteed at it sees them all. The writer records it beside the version it applied.

        Why not strong consistency on every read: a strong read waits for the server's next time tick
        (200 ms by default), and a /locate makes several reads (docs/milvus.md measures it); a read at a
        recorded timestamp waits only while that timestamp is in the future, right after a write. The
        allocation is the connection's ``alloc_timestamp`` (pymilvus pinned: ``MilvusClient`` does not
        expose it)."""
        return int(self._call("take a timestamp", lambda c: c._get_connection().alloc_timestamp(timeout=self.timeout)))

    def read_after(self, ts: int | None) -> None:
        """Reads from now on see every write before server timestamp ``ts`` (None: every write, strongly)."""
        self.read_ts = ts

    def _consistency(self) -> dict[str, Any]:
        if self.read_ts is None:
            return {"consistency_level": "Strong"}
        return {"consistency_level": "Customized", "guarantee_timestamp": self.read_ts}

    def drop(self) -> None:
        """Remove the collection from the server (a writer refilling it from the store starts here)."""
        self._call("drop the collection", lambda c: c.drop_collection(self.collection, timeout=self.timeout))
        self._client = None
        self.created = False

    def settle(self, timeout: float = 600.0) -> int:
        """Seal what was written and wait until the server's index covers every row; returns the rows indexed.

        Why: Milvus searches the rows of a growing segment by a brute-force scan and builds its HNSW only on
        sealed segments, which it seals by size or after a while; a measure of the index itself (the bench)
        seals them first, as a collection long in service has."""
        self._call("seal the segments", lambda c: c.flush(self.collection, timeout=self.timeout))
        deadline = time.monotonic() + timeout
        while True:
            info = self._call(
                "describe the index", lambda c: c.describe_index(self.collection, "code", timeout=self.timeout)
            )
            if int(info.get("pending_index_rows", 0)) == 0 and int(info.get("indexed_rows", 0)) >= int(
                info.get("total_rows", 0)
            ):
                return int(info.get("indexed_rows", 0))
            if time.monotonic() > deadline:
                raise IndexUnavailable(f"the Milvus server indexed {info.get('indexed_rows')} rows in {timeout:.0f} s")
            time.sleep(1.0)

    def close(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            with contextlib.suppress(Exception):  # already gone: nothing to close
                client.close()

    # -- the protocol -----------------------------------------------------------------------------------
    @property
    def is_trained(self) -> bool:
        return True

    def train(self, x: np.ndarray) -> None:
        """Nothing to train: HNSW and the binary scan learn nothing from the codes."""

    def _prepare(self, x: np.ndarray) -> np.ndarray:
        return checked_codes(x, self.dim, self.binary)

    def _vectors(self, x: np.ndarray) -> list:
        return [row.tobytes() for row in x] if self.binary else x.tolist()

    def add(self, ids: np.ndarray, x: np.ndarray, positions: np.ndarray | None = None) -> None:
        """Upserts: an id the server holds already is replaced, so a replayed change is harmless.
        ``positions``: (n, 2) latitude and longitude of each reference, required (the region filter reads them)."""
        ids = np.ascontiguousarray(ids, dtype=np.int64)
        x = self._prepare(x)
        if positions is None:
            raise ValueError("the milvus kind stores each reference's position: add needs positions")
        positions = np.asarray(positions, np.float64).reshape(-1, 2)
        if len(positions) != len(ids) or not np.isfinite(positions).all():
            raise ValueError(f"{len(ids)} ids need as many finite (lat, lon) positions, not {len(positions)}")
        for s in range(0, len(ids), BATCH):
            chunk = zip(
                ids[s : s + BATCH].tolist(),
                self._vectors(x[s : s + BATCH]),
                positions[s : s + BATCH].tolist(),
                strict=True,
            )
            rows = [{"id": int(i), "code": v, "lat": lat, "lon": lon} for i, v, (lat, lon) in chunk]
            self._call("store codes", lambda c, rows=rows: c.upsert(self.collection, rows, timeout=self.timeout))

    def _present(self, ids: list[int]) -> list[int]:
        found: list[int] = []
        for s in range(0, len(ids), BATCH):
            chunk = ids[s : s + BATCH]
            rows = self._call(
                "read ids",
                lambda c, chunk=chunk: c.query(
                    self.collection, filter=f"id in {chunk}", output_fields=["id"], timeout=self.timeout
                ),
            )
            found += [int(r["id"]) for r in rows]
        return found

    def remove(self, ids) -> int:
        """Deleted on the server at once (no tombstones here); returns how many were stored.

        The read first is strong (it waits for the server's next time tick, about 200 ms) and is what makes
        the delete hold: Milvus drops a delete of a key no segment holds yet, and one added an instant
        before may not be in one (deleting every id asked without the read left some in place)."""
        ids = sorted({int(i) for i in ids})
        present = self._present(ids)
        for s in range(0, len(present), BATCH):
            chunk = present[s : s + BATCH]
            self._call(
                "delete codes", lambda c, chunk=chunk: c.delete(self.collection, ids=chunk, timeout=self.timeout)
            )
        return len(present)

    def compact(self) -> None:
        """The server compacts its own segments."""

    def removed_ids(self) -> np.ndarray:
        return np.zeros(0, np.int64)

    @property
    def compaction_due(self) -> bool:
        return False

    def _to_scores(self, d: np.ndarray) -> np.ndarray:
        if self.binary:
            return 1.0 - np.asarray(d, np.float32) / self.dim
        return np.clip((1.0 + np.asarray(d, np.float32)) / 2.0, 0.0, 1.0).astype(np.float32)

    def search(
        self,
        q: np.ndarray,
        k: int,
        allowed: np.ndarray | None = None,
        box: tuple[float, float, float, float] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Top ``k`` per query, best first, -1 padded. ``box`` (min_lon, min_lat, max_lon, max_lat: the region
        filter) and ``allowed`` (ids) become a filter expression: where it passes at most ``exact_filtered``
        references they are all read and scored exactly here, else the server applies it inside its search."""
        q = self._prepare(q)
        nq = len(q)
        scores = np.zeros((nq, k), np.float32)
        out_ids = np.full((nq, k), -1, np.int64)
        if k <= 0:
            return scores, out_ids
        terms = []
        if allowed is not None:
            allowed = np.unique(np.asarray(allowed, np.int64))
            if not len(allowed):
                return scores, out_ids
            terms.append(f"id in {allowed.tolist()}")
        if box is not None:
            terms.append(box_expression(box))
        expr = " and ".join(f"({t})" for t in terms)
        if expr and self._count(expr) <= self.exact_filtered:
            return self._search_exactly(q, k, expr)
        metric = "HAMMING" if self.binary else "IP"
        params: dict[str, Any] = {"metric_type": metric}
        if not self.binary:
            params["params"] = {"ef": max(self.filtered_ef if expr else self.ef_search, k)}
        hits = self._call(
            "search",
            lambda c: c.search(
                self.collection,
                data=self._vectors(q),
                limit=k,
                filter=expr,
                search_params=params,
                output_fields=[],
                timeout=self.timeout,
                **self._consistency(),
            ),
        )
        for r, row in enumerate(hits):
            row = list(row)[:k]
            if row:
                out_ids[r, : len(row)] = [int(h["id"]) for h in row]
                scores[r, : len(row)] = self._to_scores([h["distance"] for h in row])
        return scores, out_ids

    def _count(self, expr: str) -> int:
        """How many stored references pass ``expr`` (a scan of the scalar fields on the server)."""
        rows = self._call(
            "count",
            lambda c: c.query(
                self.collection, filter=expr, output_fields=["count(*)"], timeout=self.timeout, **self._consistency()
            ),
        )
        return int(rows[0]["count(*)"]) if rows else 0

    def _search_exactly(self, q: np.ndarray, k: int, expr: str) -> tuple[np.ndarray, np.ndarray]:
        """``search`` among the references passing ``expr``, every one scored here from its code."""
        rows = self._call(
            "read codes",
            lambda c: c.query(
                self.collection,
                filter=expr,
                output_fields=["id", "code"],
                limit=max(1, self.exact_filtered),
                timeout=self.timeout,
                **self._consistency(),
            ),
        )
        scores = np.zeros((len(q), k), np.float32)
        out_ids = np.full((len(q), k), -1, np.int64)
        if not rows:
            return scores, out_ids
        ids = np.array([int(r["id"]) for r in rows], np.int64)
        codes = np.stack([self._decode(r["code"]) for r in rows])
        for n, query in enumerate(q):
            s = self._scores(query, codes)
            best = np.lexsort((ids, -s))[:k]  # best first; ties by id, as a stable order
            scores[n, : len(best)], out_ids[n, : len(best)] = s[best], ids[best]
        return scores, out_ids

    def _decode(self, code) -> np.ndarray:
        """One stored code as the server returns it (bytes in a list for a binary vector)."""
        if self.binary:
            code = code[0] if isinstance(code, list) else code
            return np.frombuffer(bytes(code), np.uint8)
        return np.asarray(code, np.float32)

    def _scores(self, query: np.ndarray, codes: np.ndarray) -> np.ndarray:
        """Exact scores of one prepared query row against stored codes."""
        if self.binary:
            return self._to_scores((np.unpackbits(codes, axis=1) != np.unpackbits(query)).sum(axis=1))
        return self._to_scores(codes @ query)

    def reconstruct(self, ids) -> np.ndarray:
        """Stored codes of ``ids``, in order (an id not stored: a ``KeyError``)."""
        ids = [int(i) for i in ids]
        width = self.dim // 8 if self.binary else self.dim
        out = np.zeros((len(ids), width), np.uint8 if self.binary else np.float32)
        if not ids:
            return out
        by_id = {}
        for s in range(0, len(ids), BATCH):
            chunk = ids[s : s + BATCH]
            rows = self._call(
                "read codes",
                lambda c, chunk=chunk: c.query(
                    self.collection,
                    filter=f"id in {chunk}",
                    output_fields=["id", "code"],
                    timeout=self.timeout,
                    **self._consistency(),
                ),
            )
            for row in rows:
                by_id[int(row["id"])] = self._decode(row["code"])
        for n, i in enumerate(ids):
            out[n] = by_id[i]
        return out

    def score_ids(self, q: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """Exact scores against stored ``ids`` (the two-stage re-rank), computed here from their codes."""
        return self._scores(self._prepare(q)[0], self.reconstruct(ids))

    def ids(self) -> np.ndarray:
        out: list[int] = []

        def read(c) -> None:
            it = c.query_iterator(self.collection, batch_size=BATCH, filter="id >= 0", output_fields=["id"])
            try:
                while batch := it.next():
                    out.extend(int(r["id"]) for r in batch)
            finally:
                it.close()

        self._call("list ids", read)
        return np.sort(np.array(out, np.int64))

    @property
    def size(self) -> int:
        rows = self._call(
            "count",
            lambda c: c.query(
                self.collection, filter="", output_fields=["count(*)"], timeout=self.timeout, **self._consistency()
            ),
        )
        return int(rows[0]["count(*)"]) if rows else 0

    def copy(self) -> MilvusIndex:
        """The same shared index: there is no copy of a server's collection to take (nothing snapshots it)."""
        return self

    def dump(self, path: Path) -> None:
        raise SharedIndexNotSnapshotted(f"the milvus index lives on the server ({self.collection}): no snapshot")

    def stage_dump(self, path: Path) -> StagedDump:
        self.dump(path)
        return StagedDump()

    def load(self, path: Path) -> None:
        raise SharedIndexNotSnapshotted(f"the milvus index lives on the server ({self.collection}): no snapshot")

    def stats(self) -> dict[str, Any]:
        """Never fails: an unreachable server is reported in the stats (/ready says so instead of erroring)."""
        try:
            size = self.size
            reachable, why = True, None
        except IndexUnavailable as e:
            size, reachable, why = -1, False, str(e)
        return {
            "kind": self.kind,
            "binary": self.binary,
            "dim": self.dim,
            "trained": True,
            "size": size,
            "tombstones": 0,
            "uri": public_uri(self.uri),
            "collection": self.collection,
            "quantizer": "BIN_FLAT" if self.binary else "HNSW",
            "m": None if self.binary else self.m,
            "reachable": reachable,
            **({"error": why} if why else {}),
        }


register_index_kind(MilvusIndex.kind, MilvusIndex)

"""Claims: pending rows a bulk run encodes itself are hidden from the worker's queue until their lease ends."""

import numpy as np
import pytest

from app.storage.store import NewReference, ReferenceStore

#: Every test here runs on SQLite and on PostgreSQL (the ``backend`` fixture).
pytestmark = pytest.mark.usefixtures("backend")


def _pending(store: ReferenceStore, n: int) -> list[int]:
    rng = np.random.default_rng(0)
    items = [NewReference(rng.bytes(64), "jpg", 40.0, -75.0) for _ in range(n)]
    return [i for i, _ in store.add_many(items)[0]]


def test_claimed_rows_leave_the_queue_until_released_or_expired(tmp_path):
    store = ReferenceStore(tmp_path)
    ids = _pending(store, 5)
    store.claim(ids[:3], "run-a", lease_s=600)
    assert [i for i, _ in store.pending(10)] == ids[3:]

    store.claim(ids[:2], "run-b", lease_s=600)  # another owner cannot take a live claim
    store.release("run-b")
    assert [i for i, _ in store.pending(10)] == ids[3:]

    store.release("run-a", ids[:1])
    assert [i for i, _ in store.pending(10)] == [ids[0], *ids[3:]]
    store.release("run-a")
    assert [i for i, _ in store.pending(10)] == ids


def test_a_crashed_runs_claims_expire_and_another_owner_takes_them_over(tmp_path):
    store = ReferenceStore(tmp_path)
    ids = _pending(store, 3)
    store.claim(ids, "crashed", lease_s=0)  # the lease is over at once
    assert [i for i, _ in store.pending(10)] == ids
    store.claim(ids[:1], "next", lease_s=600)
    assert [i for i, _ in store.pending(10)] == ids[1:]
    assert store.db.execute("SELECT owner FROM claims WHERE ref_id=?", (ids[0],)).fetchone()[0] == "next"

"""The index kind chosen by size, on real photos' codes and real FAISS: a collection of
hybrid-bin codes (float and binary, both ``flat``) crosses a lowered ``IndexSizing.switch_at``, the
compressed kinds are trained on its own codes and built in the background while the exact index keeps
answering and taking changes, the swap replays what arrived meanwhile, deletes still work after it, and a
restart comes back with the same kinds from the snapshot."""

import contextlib
import json
import threading
import time

import pytest

from app.engine.configs import get_config
from app.engine.index.references import ReferenceIndex
from app.policies import IndexSizing, SnapshotPolicy
from app.storage.snapshots import MANIFEST
from app.storage.store import ReferenceStore
from app.usecases.collection import Collection
from tests.storage.test_store import fitted  # noqa: F401  (the module's fitted pipeline and codes)
from tests.usecases.test_collection import _fill

pytestmark = pytest.mark.usefixtures("backend")

SWITCH_AT = 8
MODES = ("float", "binary", "two-stage")


def _first(col, code, mode) -> int:
    _, ids = col.search(code.float_, code.binary, 1, mode)
    return int(ids[0]) if len(ids) else -1


def _all_found_first(col, ids, codes) -> None:
    for ref_id, code in zip(ids, codes, strict=True):
        for mode in MODES:
            assert _first(col, code, mode) == ref_id, (ref_id, mode, col.index.kinds())


class HeldStream:
    """The store's real code stream, held open after it began (its version is fixed) until ``release``: the
    test's changes then land while the compressed index is being built, and must be replayed at the swap."""

    def __init__(self, store):
        self.store, self.opened, self.release = store, threading.Event(), threading.Event()
        self.real = store.code_stream

    @contextlib.contextmanager
    def __call__(self, *args, **kwargs):
        with self.real(*args, **kwargs) as stream:
            self.opened.set()
            assert self.release.wait(60)
            yield stream


def test_switch_by_size_while_serving_then_restart(tmp_path, fitted):  # noqa: F811
    pipe, rows, codes = fitted
    assert len(rows) >= SWITCH_AT + 4
    col = Collection(ReferenceStore(tmp_path), pipe, SnapshotPolicy(every_changes=1000), sizing=IndexSizing(SWITCH_AT))
    ids = _fill(col.store, rows, codes, SWITCH_AT - 1)
    col.catch_up()
    assert col.index.kinds() == {"float": "flat", "binary": "flat"} and not col.switching
    assert col.index_choice() == f"exact below {SWITCH_AT} references, then ivf-rabitq / binary-ivf"

    held = HeldStream(col.store)
    col.store.code_stream = held
    ids += _fill(col.store, rows, codes, 1, start=SWITCH_AT - 1)
    col.catch_up()  # the size reaches the threshold: the switch starts in the background
    assert held.opened.wait(120), "the switch never read the store's codes"
    assert col.switching and "switching now" in col.index_choice()
    # Meanwhile the exact index answers and takes changes (logged after the stream's version).
    assert col.index.is_exact
    _all_found_first(col, ids, codes[:SWITCH_AT])
    ids += _fill(col.store, rows, codes, 2, start=SWITCH_AT)
    gone = ids[3]
    col.store.delete(gone)
    col.catch_up()
    assert _first(col, codes[3], "float") != gone and _first(col, codes[SWITCH_AT + 1], "float") == ids[-1]
    held.release.set()
    col._switcher.join(120)
    col.store.code_stream = held.real

    assert col.index.kinds() == {"float": "ivf-rabitq", "binary": "binary-ivf"} and col.stats.kind_switches == 1
    assert col.index.stats()["float"]["nlist"] >= 1 and col.index.stats()["float"]["shortlist"] == 100
    assert col.version == col.store.head()[0] and col.size == len(ids) - 1 and gone not in col.index.ids()
    live = [i for i in ids if i != gone]
    live_codes = [c for i, c in zip(ids, codes, strict=False) if i != gone]
    _all_found_first(col, live, live_codes)
    assert col.index_choice() == f"ivf-rabitq / binary-ivf: switched from exact at {SWITCH_AT} references"
    # Deletes after the switch: removed in place, gone from the next search in every mode.
    col.store.delete(live[0])
    col.catch_up()
    assert all(_first(col, live_codes[0], m) != live[0] for m in MODES) and col.size == len(live) - 1

    # The switch made a snapshot due; it records the kinds, and a restart serves them without a rebuild,
    # whatever its own threshold (the compressed kind never switches back).
    assert col.snapshot_due() and col.write_snapshot()
    files = json.loads((tmp_path / MANIFEST).read_text())["files"]
    assert {part: f["kind"] for part, f in files.items()} == {"float": "ivf-rabitq", "binary": "binary-ivf"}
    col.store.close()
    again = Collection(ReferenceStore(tmp_path), pipe)
    assert again.stats.full_rebuilds == 0 and again.index.kinds() == {"float": "ivf-rabitq", "binary": "binary-ivf"}
    assert again.index.stats()["float"]["nlist"] == col.index.stats()["float"]["nlist"]
    _all_found_first(again, live[1:], live_codes[1:])
    assert not again.switching and again.stats.kind_switches == 0
    again.store.close()


def test_below_the_threshold_or_a_named_kind_never_switches(tmp_path, fitted):  # noqa: F811
    pipe, rows, codes = fitted
    col = Collection(ReferenceStore(tmp_path), pipe, sizing=IndexSizing(0))
    _fill(col.store, rows, codes, SWITCH_AT)
    col.catch_up()
    assert not col.switching and not col.switch_index_kind() and col.index.is_exact
    assert col.index_choice() == "exact at every size (GEOLOC_INDEX_SWITCH_AT=0)"
    col.store.close()
    # A configuration that names its kinds (the -ivf ones), or turns the size rule off, keeps them.
    sizing = IndexSizing(1)
    for config in (get_config("hybrid-bin-ivf"), get_config("hybrid-bin").model_copy(update={"index_by_size": False})):
        index = ReferenceIndex(config, 64, 64)
        assert not index.switches_by_size and not sizing.due(index)
        assert sizing.describe(index, False) == "the configuration's kinds at every size"


def test_index_at_size_builds_the_sizes_kind_now_and_says_how_far_it_is(tmp_path, fitted):  # noqa: F811
    """What a start and the end of a bulk ingest wait for: the switch run now, its progress lines handed
    over while it runs (training, then references added), the compressed kinds serving when it returns."""
    pipe, rows, codes = fitted
    col = Collection(ReferenceStore(tmp_path), pipe, sizing=IndexSizing(0))
    ids = _fill(col.store, rows, codes, SWITCH_AT + 2)
    col.catch_up()
    assert col.index_at_size(lambda line: None) and col.index.is_exact  # the switch is off: nothing due
    col.sizing = IndexSizing(SWITCH_AT)
    held = HeldStream(col.store)
    col.store.code_stream = held
    lines: list[str] = []

    def release_once_trained() -> None:  # the stream opens after the training: hold it a few polls, then go on
        assert held.opened.wait(120)
        time.sleep(0.5)
        held.release.set()

    releaser = threading.Thread(target=release_once_trained)
    releaser.start()
    assert col.index_at_size(lines.append, poll_seconds=0.05)
    releaser.join()
    col.store.code_stream = held.real
    assert col.index.kinds() == {"float": "ivf-rabitq", "binary": "binary-ivf"} and not col.switching
    assert lines[0].startswith(f"building the index {SWITCH_AT + 2:,} references call for")
    assert any(": training on " in line for line in lines), lines
    assert len(lines) == len(set(lines))  # each line handed over once
    assert col.switch_progress is None
    _all_found_first(col, ids, codes[: SWITCH_AT + 2])
    col.store.close()

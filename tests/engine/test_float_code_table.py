"""The float code table of ``ivf-rabitq``: codes read from the index's file and a spill file
by ``pread``, never held in the heap; puts, drops and replacements against a plain dict; a snapshot written
from the served index itself (``stage_dump``) while changes keep arriving, then read back."""

import os
from pathlib import Path

import numpy as np
import pytest

from app.engine.index.float_code_table import FloatCodeTable, RowFile, use_spill_dir
from app.engine.index.kinds.ivf_rabitq import IvfCompressedIndex
from tests.engine.test_ivf_compressed import clustered


def _check(table, model: dict[int, np.ndarray]) -> None:
    ids = np.array(sorted(model), np.int64)
    assert np.array_equal(table.live_ids(), ids)
    if len(ids):
        shuffled = np.random.default_rng(len(ids)).permutation(ids)
        assert np.array_equal(table.get(shuffled), np.stack([model[int(i)] for i in shuffled]))


def test_row_file_reads_any_rows_in_the_order_asked(tmp_path):
    rows = np.arange(300 * 8, dtype=np.float32).reshape(300, 8)
    spill = RowFile.spill(8)
    assert np.array_equal(spill.append(rows[:100]), np.arange(100)) and spill.append(rows[100:]).tolist() == list(
        range(100, 300)
    )
    ask = np.array([299, 0, 5, 6, 7, 150, 5, 40, 41, 298])  # runs, far rows, a repeat
    assert np.array_equal(spill.read(ask), rows[ask])
    path = tmp_path / "rows"
    path.write_bytes(b"x" * 24 + rows.tobytes())
    assert np.array_equal(RowFile.open(path, 24, 8, 300).read(ask), rows[ask])
    with pytest.raises(OSError, match="past the end"):
        RowFile.open(path, 24, 8, 300).read(np.array([300]))


def test_puts_drops_and_replacements_match_a_dict_through_snapshots(tmp_path):
    """Random changes, and at random points a snapshot of the table (written from a copy while the table
    keeps changing, then ``rebase``); the table answers what a dict of the same changes holds."""
    rng = np.random.default_rng(0)
    index = IvfCompressedIndex(16, nlist=4)
    index.train(rng.standard_normal((400, 16)).astype(np.float32))
    table, model = index.table, {}
    for step in range(60):
        ids = np.unique(rng.integers(0, 3000, rng.integers(1, 300)))
        if rng.random() < 0.6:
            codes = rng.standard_normal((len(ids), 16)).astype(np.float32)
            table.put(ids, codes)
            model.update(zip(ids.tolist(), codes, strict=True))
        else:
            table.drop(ids)
            for i in ids.tolist():
                model.pop(i, None)
        if step % 9 == 4:  # a snapshot: copy, then changes meanwhile, then the file written and adopted
            frozen, frozen_model = table.copy(), dict(model)
            more = np.unique(rng.integers(0, 3000, 50))
            table.drop(more[::2])
            new = rng.standard_normal((len(more[1::2]), 16)).astype(np.float32)
            table.put(more[1::2], new)
            for i in more[::2].tolist():
                model.pop(i, None)
            model.update(zip(more[1::2].tolist(), new, strict=True))
            path = tmp_path / f"t{step}"
            with open(path, "wb") as f:
                f.write(b"\0" * 8)
                frozen.write(f)
            _check(type(table).read(path, 8), frozen_model)  # the file holds the table as it was copied
            table.rebase(type(table).read(path, 8), frozen)
            assert table.where()[1] <= len(more)  # only the changes made meanwhile are spilled
        _check(table, model)
    with pytest.raises(KeyError):
        table.get(np.array([5000]))


def test_snapshot_from_the_served_index_while_it_changes(tmp_path):
    """``stage_dump`` writes FAISS's part at once and the float codes afterwards (the collection's lock is
    released between): changes made in between are not in the file, are kept by the served index after
    ``adopt``, and a load of the file answers as the index did when staged."""
    codes = clustered(3000)
    index = IvfCompressedIndex(256, nlist=32, nprobe=32)
    index.train(codes)
    index.add(np.arange(2500), codes[:2500])
    q = codes[100:160]
    before = index.search(q, 10)
    path = tmp_path / "float.faiss"
    staged = index.stage_dump(path)
    index.add(np.arange(2500, 3000), codes[2500:])  # meanwhile: new references, a removal, a replacement
    index.remove([100, 101])
    index.add(np.array([102]), codes[2999:3000])
    staged.finish()
    staged.adopt(path)
    assert index.table.where() == (2500 - 3, 500 + 1)  # the file minus the changed ids; new and replaced spilled
    assert np.array_equal(index.table.get(np.array([102])), codes[2999:3000])
    assert np.array_equal(index.table.get(np.array([7, 2700])), codes[[7, 2700]])
    after = index.search(codes[2600:2610], 1)[1][:, 0]
    assert np.array_equal(after, np.arange(2600, 2610))

    loaded = IvfCompressedIndex(256, nprobe=32)
    loaded.load(path)
    assert loaded.size == 2500 and loaded.table.where() == (2500, 0)
    assert np.array_equal(loaded.search(q, 10)[1], before[1])
    assert np.allclose(loaded.search(q, 10)[0], before[0])


def test_no_code_is_mapped_into_the_process(tmp_path):
    """The float codes are read by ``pread``: after a load and searches, the process maps nothing of the
    file (a mapping made the pages a reader touched resident in it, about a megabyte per code read)."""
    codes = clustered(2000)
    index = IvfCompressedIndex(256, nlist=16, nprobe=16)
    index.train(codes)
    index.add(np.arange(2000), codes)
    path = tmp_path / "float.faiss"
    index.dump(path)
    loaded = IvfCompressedIndex(256, nprobe=16)
    loaded.load(path)
    loaded.search(codes[:20], 5)
    maps = Path(f"/proc/{os.getpid()}/maps").read_text()
    assert str(path) not in maps and "geoloc-float-codes" not in maps


def test_a_file_in_the_layout_main_wrote_loads(tmp_path):
    """The file layout is unchanged (header, FAISS's serialised index, padding to 8 bytes, then count, dim,
    sorted ids and their codes): a file put together by hand in that layout, as the memory-mapping version
    wrote it, loads and answers as the index it was made from."""
    import struct

    import faiss

    codes = clustered(1500)
    index = IvfCompressedIndex(256, nlist=16, nprobe=16)
    index.train(codes)
    ids = np.arange(1000, 2500)
    index.add(ids, codes)
    faiss_part = faiss.serialize_index(index._index).tobytes()
    table_at = 24 + len(faiss_part) + (-(24 + len(faiss_part)) % 8)
    path = tmp_path / "float-g0-v9.faiss"
    with open(path, "wb") as f:
        f.write(struct.pack("<8sQQ", b"GEOIVFC1", len(faiss_part), table_at))
        f.write(faiss_part)
        f.write(b"\0" * (table_at - f.tell()))
        f.write(struct.pack("<QQ", len(ids), 256) + ids.astype(np.int64).tobytes() + codes.tobytes())
    loaded = IvfCompressedIndex(256, nprobe=16)
    loaded.load(path)
    assert loaded.size == 1500 and loaded.table.where() == (1500, 0)
    assert np.array_equal(loaded.table.get(ids[::-7]), codes[::-7])
    assert np.array_equal(loaded.search(codes[:50], 10)[1], index.search(codes[:50], 10)[1])


def test_spill_files_go_to_the_folder_named_and_leave_nothing_there(tmp_path):
    """The service names its data dir: a switch spills 1 KB per reference, too much for a small TMPDIR."""
    use_spill_dir(tmp_path)
    try:
        table = FloatCodeTable(4)
        table.put(np.arange(3), np.eye(3, 4, dtype=np.float32))
        target = os.readlink(f"/proc/self/fd/{table._spill.fd}")
        assert target.startswith(str(tmp_path)) and target.endswith("(deleted)")
        assert list(tmp_path.iterdir()) == []  # unlinked at once: a crash leaves nothing behind
        assert np.array_equal(table.get(np.array([2, 0])), np.eye(3, 4, dtype=np.float32)[[2, 0]])
        use_spill_dir(tmp_path / "gone")  # a folder that cannot take the file: the system's temporary folder
        other = FloatCodeTable(4)
        other.put(np.arange(1), np.ones((1, 4), np.float32))
        assert not os.readlink(f"/proc/self/fd/{other._spill.fd}").startswith(str(tmp_path))
    finally:
        use_spill_dir(None)

"""The ingestion journal: a file is known by path, size and mtime; anything else is a different file."""

from app.storage.journal import JOURNAL_NAME, FileKey, Journal


def test_lookup_finds_only_files_recorded_with_the_same_size_and_mtime(tmp_path):
    j = Journal(tmp_path)
    a, b = FileKey("/p/a.jpg", 100, 1_000), FileKey("/p/b.jpg", 200, 2_000)
    j.record([(a, 1), (b, 2)])
    assert j.lookup([a, b, FileKey("/p/c.jpg", 1, 1)]) == {"/p/a.jpg": 1, "/p/b.jpg": 2}
    assert j.lookup([FileKey("/p/a.jpg", 101, 1_000), FileKey("/p/b.jpg", 200, 2_001)]) == {}
    assert j.lookup([]) == {}
    j.close()

    again = Journal(tmp_path)  # durable: a later run reads what an earlier one wrote
    assert (tmp_path / JOURNAL_NAME).exists() and len(again) == 2
    again.record([(FileKey("/p/a.jpg", 101, 3_000), 7)])  # the file changed and became another reference
    assert again.lookup([FileKey("/p/a.jpg", 101, 3_000)]) == {"/p/a.jpg": 7}
    assert again.lookup([a]) == {}
    assert len(again) == 2

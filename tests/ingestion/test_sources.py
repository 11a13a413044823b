"""Sources: what SOURCE is (folder, CSV, manifest), read lazily, with unusable rows reported, not fatal."""

import pytest

from app.ingestion.sources import SourceError, SourceItem, open_source


def test_a_folder_yields_its_photos_recursively_in_a_stable_order(tmp_path):
    (tmp_path / "b" / "deep").mkdir(parents=True)
    for name in ("z.JPG", "a.png", "b/deep/c.heic", "b/x.webp", "notes.txt", ".hidden.jpg", "b/sidecar.xmp"):
        (tmp_path / name).write_bytes(b"x")
    src = open_source(tmp_path)
    assert src.kind == "folder" and src.exif_heading
    names = [p.path.relative_to(tmp_path).as_posix() for p in src.items()]
    assert names == ["a.png", "z.JPG", "b/x.webp", "b/deep/c.heic"]
    assert src.count() == 4
    assert all(i.lat is None and i.lon is None for i in src.items())  # positions come from EXIF


def test_a_csv_of_rows_with_relative_paths_and_optional_columns(tmp_path):
    (tmp_path / "list.csv").write_text(
        "image,lat,lon,heading,captured_at,label\n"
        "photos/a.jpg,39.95,-75.19,90,2024-09-23T16:00:00,north gate\n"
        "b.jpg,39.96,-75.18,,,\n"
        "c.jpg,123,-75.18,,,\n"
        "d.jpg,39.96,-75.18,400,,\n"
        "e.jpg,north,-75.18,,,\n"
    )
    src = open_source(tmp_path / "list.csv")
    assert src.kind == "csv" and not src.exif_heading and src.count() == 5
    a, b, c, d, e = src.items()
    assert a == SourceItem(tmp_path / "photos" / "a.jpg", 39.95, -75.19, 90.0, "2024-09-23T16:00:00", "north gate")
    assert b == SourceItem(tmp_path / "b.jpg", 39.96, -75.18)
    assert "line 4" in c.problem and "out of range" in c.problem
    assert "line 5" in d.problem and "heading" in d.problem
    assert "not numbers" in e.problem


def test_a_csv_with_a_split_column_is_a_manifest(tmp_path):
    (tmp_path / "m.csv").write_text("image,lat,lon,split,group\na.jpg,1,2,db,g\nb.jpg,3,4,query,g\nc.jpg,5,6,db,h\n")
    src = open_source(None, manifest=tmp_path / "m.csv", split="db")
    assert src.kind == "manifest" and src.count() == 2
    assert [(i.path.name, i.lat, i.label) for i in src.items()] == [("a.jpg", 1.0, "a.jpg"), ("c.jpg", 5.0, "c.jpg")]
    assert open_source(tmp_path / "m.csv", split="query").count() == 1


def test_a_source_that_cannot_be_read_is_a_clear_error(tmp_path):
    (tmp_path / "bad.csv").write_text("path,latitude\nx.jpg,1\n")
    with pytest.raises(SourceError, match=r"missing columns \['image', 'lat', 'lon'\]"):
        open_source(tmp_path / "bad.csv")
    with pytest.raises(SourceError, match="does not exist"):
        open_source(tmp_path / "nothing")
    with pytest.raises(SourceError, match="not both"):
        open_source(tmp_path, manifest=tmp_path / "bad.csv")
    with pytest.raises(SourceError, match="give SOURCE"):
        open_source(None)

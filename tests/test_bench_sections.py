"""Benchmarks share docs/benchmarks.md: each owns a marked section, and no run erases another's."""

from bench.benchmarks import write_kept
from bench.common import marked_sections, write_section


def test_sections_are_replaced_in_place_and_kept_by_the_full_render(tmp_path):
    doc = tmp_path / "benchmarks.md"
    doc.write_text("# Benchmarks\n\nold figures\n")
    write_section("scale", "## Scale\n\nfirst", doc)
    write_section("ingest", "## Ingestion\n\nrate 5", doc)
    write_section("scale", "## Scale\n\nsecond", doc)
    text = doc.read_text()
    assert text.count("<!-- scale:begin -->") == 1 and "second" in text and "first" not in text
    assert text.index("## Scale") < text.index("## Ingestion")  # replaced where it was
    assert [s.splitlines()[1] for s in marked_sections(text)] == ["## Scale", "## Ingestion"]

    doc.write_text(doc.read_text() + "\nNotes on ingestion, written by hand.\n")
    write_kept(doc, "# Benchmarks\n\nnew figures\n")
    text = doc.read_text()
    assert "new figures" in text and "old figures" not in text
    assert "second" in text and "rate 5" in text and "written by hand" in text

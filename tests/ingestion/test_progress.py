"""Progress off a terminal: one line per ``every`` images with the rate and the ETA, and a last line."""

import io

from app.engine.progress import Progress


def test_lines_every_thousand_images_and_at_the_end():
    out = io.StringIO()  # not a terminal
    p = Progress(2500, desc="ingest folder", every=1000, stream=out)
    for _ in range(25):
        p.update(100)
    p.close()
    lines = out.getvalue().splitlines()
    assert [line.split(" img")[0] for line in lines] == [
        "ingest folder: 1,000/2,500",
        "ingest folder: 2,000/2,500",
        "ingest folder: 2,500/2,500",
    ]
    assert all("img/s, ETA" in line for line in lines)
    assert lines[-1].endswith("ETA 0s")


def test_a_jump_over_several_thousands_prints_one_line():
    out = io.StringIO()
    p = Progress(10_000, every=1000, stream=out)
    p.update(3500)
    p.update(400)
    p.update(100)
    assert out.getvalue().count("\n") == 2  # at 3,500 (crossing three marks at once) and at 4,000

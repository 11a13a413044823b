"""What the ingestion journal saves on a re-run: `geoloc ingest FOLDER` again over photos already stored,
with the journal (one ``stat`` per file) against without it (every file read, decoded, validated and hashed,
then found a duplicate), timed interleaved in one process.

Why it matters: a run over 10^5-10^6 phone photos that stops (a crash, a full disk, Ctrl-C) is run again,
and without the journal the re-run re-reads everything it had already stored before it reaches new work.

    python -m bench.ingest_resume [--photos ../shared/data/penn-campus-gps/photos] [--limit 0] [--repeat 3]

The first run (which encodes) is setup, reported but not compared. Prints medians and the ratio.
"""

from __future__ import annotations

import argparse
import io
import tempfile
import time
from pathlib import Path

from app.engine.configs import DEFAULT_CONFIG
from app.engine.progress import Progress
from app.ingestion.bulk import IngestOptions, IngestRun
from app.ingestion.sources import open_source
from app.storage.journal import JOURNAL_NAME
from app.usecases.service import GeolocService
from bench.common import REPO, median_ms


def _run(service: GeolocService, folder: Path) -> tuple[float, object]:
    source = open_source(folder)
    progress = Progress(source.count(), stream=io.StringIO())  # quiet: the bench prints its own lines
    t0 = time.perf_counter()
    summary = IngestRun(service, source, IngestOptions(), progress).run()
    return (time.perf_counter() - t0) * 1000, summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photos", type=Path, default=REPO.parent / "shared" / "data" / "penn-campus-gps" / "photos")
    ap.add_argument("--models-dir", type=Path, default=REPO / "models")
    ap.add_argument("--config", default=DEFAULT_CONFIG)
    ap.add_argument("--limit", type=int, default=0, help="first N photos (0: all)")
    ap.add_argument("--repeat", type=int, default=3, help="timed re-runs of each kind")
    args = ap.parse_args()
    photos = sorted(args.photos.glob("*.jpg"))[: args.limit or None]
    with tempfile.TemporaryDirectory(prefix="geoloc-bench-ingest-") as tmp:
        folder = Path(tmp) / "photos"
        folder.mkdir()
        for p in photos:  # read in place through links: the shared data is never copied
            (folder / p.name).symlink_to(p.resolve())
        data = Path(tmp) / "data"
        service = GeolocService.open(data, args.models_dir, args.config)
        first_ms, first = _run(service, folder)
        print(
            f"{len(photos)} photos, {args.config}; first run (setup, encodes): {first.added} added, "
            f"{sum(first.skipped.values())} skipped, {first_ms / 1000:.1f} s"
        )
        times: dict[str, list[float]] = {"journal": [], "no journal": []}
        for r in range(args.repeat):
            for kind in ("journal", "no journal") if r % 2 == 0 else ("no journal", "journal"):
                if kind == "no journal":
                    for suffix in ("", "-wal", "-shm"):
                        (data / (JOURNAL_NAME + suffix)).unlink(missing_ok=True)
                ms, summary = _run(service, folder)
                assert summary.added == 0, "a re-run must add nothing"
                times[kind].append(ms)
        med = {k: median_ms(v) for k, v in times.items()}
        for k, v in med.items():
            print(f"  re-run, {k:10s} median {v:9.1f} ms ({v / len(photos):.2f} ms per photo)")
        print(f"  no journal / journal = {med['no journal'] / med['journal']:.1f}")


if __name__ == "__main__":
    main()

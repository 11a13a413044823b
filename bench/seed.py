"""Fill a data dir with N indexed references carrying synthetic codes, through the bulk path.

    .venv/bin/python -m bench.seed --data-dir D --references N [--config C] [--models-dir M]

Why synthetic: measuring the service at 10^5-10^6 references needs that many references, and encoding
real photos at 5 images/s would take days. The codes have the fitted pipeline's shapes (unit float vectors,
random bits), the positions are spread over a city-sized square, and each reference gets a tiny distinct
placeholder JPEG (a template with its number in a comment segment), so everything the service does with a
reference (rows, images, change log, snapshots) is exercised. Rows go through ``ReferenceStore.add_many``
in batches: one transaction and one folder sync per batch.
"""

from __future__ import annotations

import argparse
import io
import math
import time
from pathlib import Path

import numpy as np
from PIL import Image

from app.engine.configs import DEFAULT_CONFIG
from app.engine.pipeline import load_pipeline
from app.storage.store import NewReference, ReferenceStore

CENTRE = (39.9526, -75.1652)  # Philadelphia City Hall
SIDE_M = 10_000.0


def _template_jpeg() -> bytes:
    rng = np.random.default_rng(0)
    buf = io.BytesIO()
    Image.fromarray(rng.integers(0, 255, (32, 32, 3), dtype=np.uint8)).save(buf, "JPEG", quality=50)
    return buf.getvalue()


def placeholder(template: bytes, n: int) -> bytes:
    """The template with a COM segment naming ``n`` right after SOI: a valid, distinct JPEG."""
    text = f"geoloc synthetic reference {n}".encode()
    return template[:2] + b"\xff\xfe" + (len(text) + 2).to_bytes(2, "big") + text + template[2:]


def seed(data_dir: Path, references: int, models_dir: Path, config: str, batch: int = 10_000, seed: int = 0) -> dict:
    pipeline = load_pipeline(models_dir, config)
    store = ReferenceStore(data_dir)
    store.bind(pipeline)
    start = store.count(None)
    rng = np.random.default_rng(seed + start)
    template = _template_jpeg()
    dlat = SIDE_M / 111_320
    dlon = SIDE_M / (111_320 * math.cos(math.radians(CENTRE[0])))
    t0 = time.perf_counter()
    added = 0
    for lo in range(start, references, batch):
        n = min(batch, references - lo)
        f = None
        if pipeline.float_dim:
            f = rng.standard_normal((n, pipeline.float_dim)).astype(np.float32)
            f /= np.linalg.norm(f, axis=1, keepdims=True)
        b = rng.integers(0, 256, (n, pipeline.bits // 8), dtype=np.uint8) if pipeline.bits else None
        lats = CENTRE[0] + (rng.random(n) - 0.5) * dlat
        lons = CENTRE[1] + (rng.random(n) - 0.5) * dlon
        items = [
            NewReference(
                placeholder(template, lo + j),
                "jpeg",
                float(lats[j]),
                float(lons[j]),
                label=f"synthetic-{lo + j}",
                source="seed",
                float_code=None if f is None else f[j],
                binary_code=None if b is None else b[j],
            )
            for j in range(n)
        ]
        rows, _ = store.add_many(items)
        added += sum(created for _, created in rows)
        done = lo + n
        rate = added / (time.perf_counter() - t0)
        print(f"  {done:>9,d} references  {rate:,.0f} rows/s", flush=True)
    seconds = time.perf_counter() - t0
    store.close()
    return {"references": references, "added": added, "seconds": seconds, "rows_per_second": added / max(seconds, 1e-9)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-dir", type=Path, required=True)
    ap.add_argument("--references", type=int, required=True, help="total references the data dir should hold")
    ap.add_argument("--config", default=DEFAULT_CONFIG)
    ap.add_argument("--models-dir", type=Path, default=Path("models"))
    ap.add_argument("--batch", type=int, default=10_000)
    args = ap.parse_args()
    r = seed(args.data_dir, args.references, args.models_dir, args.config, args.batch)
    print(
        f"seeded {r['added']:,d} references into {args.data_dir} in {r['seconds']:.1f} s "
        f"({r['rows_per_second']:,.0f} rows/s)"
    )


if __name__ == "__main__":
    main()

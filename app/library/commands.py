"""`geoloc library ...`: scan a folder, review, write back, undo, export (the faces of ``app.library``).

Every failure of the library's own (a folder that cannot be scanned, a decision refused, exiftool missing)
is one ``error:`` line and exit 2, like the rest of `geoloc`; a scan that skipped bad files exits 0 and
lists them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from app.settings import Settings, usable_cpus

library_app = typer.Typer(no_args_is_help=True, help="Geolocate a photo library: scan, review, write back, export.")
_S = Settings()
Folder = Annotated[
    Path,
    typer.Argument(
        help="the library: a folder of photos (recursively), or a manifest (db rows: references; query rows: to locate)"
    ),
]
DataDir = Annotated[Path, typer.Option("--data-dir", help="the collection (the library's GPS photos go into it)")]
ModelsDir = Annotated[Path, typer.Option("--models-dir", help="built model and fitted pipelines")]
ConfigOpt = Annotated[str, typer.Option("--config", "-c", help="named pipeline configuration")]


def _fail(msg: str) -> None:
    typer.secho(f"error: {msg}", fg=typer.colors.RED, err=True)
    raise typer.Exit(2)


def _journal(data_dir: Path):
    from app.storage.library import JournalError, LibraryJournal

    try:
        return LibraryJournal(data_dir)
    except JournalError as e:  # a journal of another layout, damaged, not SQLite: one line, no traceback
        _fail(str(e))


def _scan_of(journal, folder: Path) -> str:
    sid = journal.scan_of(folder)
    if sid is None:
        _fail(f"{folder.resolve()} has not been scanned into this data dir: run `geoloc library scan` first")
    return sid


@library_app.command("scan")
def scan(
    folder: Folder,
    data_dir: DataDir = _S.data_dir,
    models_dir: ModelsDir = _S.models_dir,
    config: ConfigOpt = _S.config,
    geojson: Annotated[Path | None, typer.Option("--geojson", help="write every suggestion as GeoJSON")] = None,
    csv_out: Annotated[Path | None, typer.Option("--csv", help="write every suggestion as CSV")] = None,
    gpx: Annotated[Path | None, typer.Option("--gpx", help="write the placed suggestions as GPX waypoints")] = None,
    workers: Annotated[int, typer.Option(min=1, help="threads reading and locating")] = usable_cpus(),
    time_prior: Annotated[
        bool, typer.Option("--time-prior/--no-time-prior", help="use capture times near geotagged photos")
    ] = True,
    rerank: Annotated[bool, typer.Option("--rerank", help="geometric verification of the top candidates")] = False,
    ray: Annotated[str | None, typer.Option("--ray", help="encode the GPS photos on Ray (as geoloc ingest)")] = None,
) -> None:
    """Photos with GPS join the collection; photos without GPS are located (resumable: a second run skips
    what is done). Nothing is written into any photo: review, then `geoloc library write`."""
    from app.library.exports import write_export
    from app.library.scan import LibraryError, ScanOptions, library_files, scan_library
    from app.usecases.service import GeolocService

    if not folder.exists():
        _fail(f"{folder} does not exist: give a folder of photos or a manifest (image,lat,lon,split)")
    # The folder (or manifest) is checked before the models load: a bad path costs milliseconds, not the
    # seconds of loading the network and the index.
    try:
        files = library_files(folder.resolve(), Path(data_dir).resolve())
    except LibraryError as e:
        _fail(str(e))
    service = GeolocService.open(data_dir, models_dir, config, limits=_S.image_limits(), backend=_S.backend(data_dir))
    journal = _journal(data_dir)
    try:
        options = ScanOptions(workers=workers, time_prior=time_prior, rerank=rerank, ray=ray)
        typer.echo(f"library {folder.resolve()}: {workers} threads on {usable_cpus()} usable CPUs")
        try:
            s = scan_library(service, folder, options, journal, say=typer.echo, files=files)
        except LibraryError as e:
            for path, reason in e.problems:
                typer.echo(f"skipped {path}: {reason}")
            _fail(str(e))
        typer.echo(
            f"{s.photos} photos: {s.references} references (with a position), {s.located} located now, "
            f"{s.unchanged} done by an earlier run; {s.placed} placed, {s.confident} confident"
            + (f"; {s.by_sequence} placed by the run of photos around them" if s.by_sequence else "")
        )
        for path, reason in s.problems:
            typer.echo(f"skipped {path}: {reason}")
        records = journal.photos(s.scan_id)
        for fmt, out in (("geojson", geojson), ("csv", csv_out), ("gpx", gpx)):
            if out is not None:
                n = write_export(records, fmt, True, out)
                typer.echo(f"wrote {out} ({n} photos without GPS)")
    finally:
        journal.close()


@library_app.command("list")
def list_cmd(folder: Folder, data_dir: DataDir = _S.data_dir) -> None:
    """Every located photo of the library, one JSON line each (id, file, suggestion, decision)."""
    from app.storage.library import LOCATED

    journal = _journal(data_dir)
    try:
        for rec in journal.photos(_scan_of(journal, folder), LOCATED):
            typer.echo(json.dumps({"id": rec.id, "decision": rec.decision, **rec.result}))
    finally:
        journal.close()


@library_app.command("decide")
def decide_cmd(
    folder: Folder,
    photo: Annotated[Path, typer.Argument(help="the photo (its path, as `geoloc library list` prints it)")],
    action: Annotated[str, typer.Argument(help="accept, reject, move or clear")],
    lat: Annotated[float | None, typer.Option(help="with move: the position")] = None,
    lon: Annotated[float | None, typer.Option()] = None,
    data_dir: DataDir = _S.data_dir,
) -> None:
    """Accept the suggestion, move the pin (--lat --lon), reject, or clear the decision. Writes nothing."""
    from app.library.review import DecisionError, decide

    journal = _journal(data_dir)
    try:
        sid = _scan_of(journal, folder)
        rec = journal.known(sid).get(str(photo.resolve()))
        if rec is None:
            _fail(f"{photo} is not a photo of this library")
        try:
            got = decide(journal, sid, rec.id, action, lat, lon)
        except DecisionError as e:
            _fail(str(e))
        typer.echo(f"{got.path}: {got.decision or 'undecided'}" + (f" at {got.lat},{got.lon}" if got.lat else ""))
    finally:
        journal.close()


@library_app.command("write")
def write_cmd(
    folder: Folder,
    data_dir: DataDir = _S.data_dir,
    in_file: Annotated[bool, typer.Option("--in-file", help="EXIF GPS in the photo itself (pixels untouched)")] = False,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="say what would be written, write nothing")] = False,
) -> None:
    """Write the accepted positions with exiftool: XMP sidecars (IMG.jpg.xmp) by default."""
    from app.library.writeback import WriteBackError, write_back

    journal = _journal(data_dir)
    try:
        try:
            out = write_back(journal, _scan_of(journal, folder), data_dir, in_file, dry_run)
        except WriteBackError as e:
            _fail(str(e))
        verb = "would write" if dry_run else "wrote"
        for w in out["written"]:
            typer.echo(f"{verb} {w['target']}: {w['lat']},{w['lon']}")
        for f in out["failed"]:
            typer.echo(f"not written {f['file']}: {f['reason']}")
        if dry_run:
            for path in out["withdrawn"]:
                typer.echo(f"would undo the write of {path} (no longer accepted)")
        else:
            _say_undo(out["withdrawn"], "no longer accepted: ")
        typer.echo(f"{len(out['written'])} {verb}, {len(out['failed'])} failed")
    finally:
        journal.close()


@library_app.command("undo")
def undo_cmd(folder: Folder, data_dir: DataDir = _S.data_dir) -> None:
    """Undo every write of this library (sidecars removed or restored, photos restored byte for byte)."""
    from app.library.writeback import undo

    journal = _journal(data_dir)
    try:
        out = undo(journal, _scan_of(journal, folder))
        _say_undo(out)
        typer.echo(f"{len(out['restored'])} writes undone")
    finally:
        journal.close()


def _say_undo(out: dict, why: str = "") -> None:
    """One line per restored, skipped (changed since our write) and failed target of an undo."""
    for t in out["restored"]:
        typer.echo(f"{why}restored {t}")
    for s in out["skipped"]:
        typer.echo(f"{why}skipped {s['target']}: {s['reason']}")
    for f in out["failed"]:
        typer.echo(f"{why}not restored {f['target']}: {f['reason']}")


@library_app.command("export")
def export_cmd(
    folder: Folder,
    data_dir: DataDir = _S.data_dir,
    geojson: Annotated[Path | None, typer.Option("--geojson")] = None,
    csv_out: Annotated[Path | None, typer.Option("--csv")] = None,
    gpx: Annotated[Path | None, typer.Option("--gpx")] = None,
    everything: Annotated[bool, typer.Option("--all", help="every suggestion, not only the accepted")] = False,
) -> None:
    """The accepted positions (or, with --all, every suggestion with its radius) as GeoJSON, CSV, GPX."""
    from app.library.exports import write_export

    if geojson is None and csv_out is None and gpx is None:
        _fail("give at least one of --geojson, --csv, --gpx")
    journal = _journal(data_dir)
    try:
        records = journal.photos(_scan_of(journal, folder))
        for fmt, out in (("geojson", geojson), ("csv", csv_out), ("gpx", gpx)):
            if out is not None:
                typer.echo(f"wrote {out} ({write_export(records, fmt, everything, out)} photos)")
    finally:
        journal.close()

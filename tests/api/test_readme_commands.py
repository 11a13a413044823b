"""The commands of the README and of docs/*.md, run the way the pages write them, in a shell, on real photos.

Each line of the pages' ``sh`` blocks (README.md first, then docs/ by name) that starts with ``curl`` or
``geoloc`` runs in bash after the README's own set-up line (``source .venv/bin/activate``, from the checkout;
``geoloc`` is not on the PATH before it) and ``KEY=$(geoloc api-key)``. The files the lines name (photo.jpg,
a.jpg, b.jpg, c.jpg, phone-photo-with-gps.jpg, survey.csv, ~/photos) are real penn-campus-gps photos put under those
names in the shell's folder. A synopsis line runs in its shortest form: its optional ``[...]`` parts left out.

The only rewrites are the ones a reader makes too (``PLACEHOLDERS``): the server's address (a free port
instead of 8000), the job id the README writes JOB_ID, a manifest for M, and temporary folders for
/backups/ and D2. The environment sets what the README says it sets (GEOLOC_DATA_DIR and friends): the
service's data dir is a copy of the session's mini collection (30 references, so reference 12 exists).

Lines that need a cluster, a long fit or a second server are run by the test named in ``ELSEWHERE``; a
line in neither list fails the test, so a new README command cannot go untried."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.api.conftest import CONFIG, Server
from tests.conftest import PENN, REPO, SHARED

README = (REPO / "README.md").read_text()
#: Every page whose ``sh`` blocks a reader runs: the README, then docs/ by name (api.md's curl lines in order).
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
DOCS = "\n".join(page.read_text() for page in PAGES)
API_DOC = (REPO / "docs" / "api.md").read_text()
ACTIVATE = "source .venv/bin/activate"

#: README lines run by other tests (their commands there are the same, through `python -m app.cli`).
#: The README's library lines run, in order and on a library of real photos, in their own test.
LIBRARY = "tests/library/test_readme_library.py"
ELSEWHERE = {
    "geoloc models build": "tests/test_cli.py (test_build_fit_ingest_locate), tests/engine/test_xfeat_onnx.py",
    "geoloc fit --manifest M --config hybrid": "tests/test_cli.py (fit, with and without the SVM bank)",
    "geoloc eval --manifest M --config C": "tests/test_cli.py (test_eval_writes_the_report)",
    "geoloc refit": "tests/api/test_refit.py",
    "geoloc features backfill": "tests/api/test_stored_features_ops.py, tests/api/test_hardening_round4_ops.py "
    "(a configuration that stores features)",
    "geoloc serve": "every tests/service server (tools/server_process.py runs `geoloc serve`)",
    "geoloc worker | check | backup DEST | restore SRC": "a synopsis of the lines of 'The data dir', run here",
    "geoloc ingest SOURCE": "a synopsis: its forms (a folder, a CSV, --manifest) are run here",
    "geoloc ingest ~/photos --ray local": "tests/api/test_ingest_ray.py (a local Ray instance)",
    "geoloc ingest ~/photos --ray auto": "needs a running Ray cluster (tests/api/test_ingest_ray.py: --ray local)",
    "geoloc ingest ~/photos --ray ray://head:10001 --workers 32": "needs a remote Ray cluster",
    "geoloc ingest ~/photos --data-dir /var/lib/geoloc": "tests/api/test_postgres_hosts.py (ingest into "
    "PostgreSQL: operations.md's 'Several hosts' block needs a database server)",
    "geoloc serve --data-dir /var/lib/geoloc": "tests/api/test_postgres_hosts.py (two servers on PostgreSQL)",
    "geoloc locate --sequence walk/": "tests/test_cli_sequence.py (test_a_folder_is_read_in_exif_time_order)",
    "geoloc locate --sequence walk/ --brief": "tests/test_cli_sequence.py (a folder of real photos)",
    "geoloc locate --video ride.mp4 --every 2": "tests/test_cli_sequence.py (test_a_video_every_second)",
    "geoloc eval -m out/walks/penn-walks-0.csv --sequence-window 5 --cache out/cache --json out/walks/eval-0-w5.json": (
        "tests/test_eval_sequence.py (a walk manifest from bench/sequence_walks.py, evaluated with a window)"
    ),
    "geoloc eval -m out/walks/penn-walks-0.csv --sequence-window 5 --svm-bank positive --svm-bank-source collection "
    "--cache out/cache --json out/walks/eval-0-w5-bank.json": "tests/test_eval_sequence.py (the same, another bank)",
    "geoloc library scan ~/library --data-dir D --geojson out.geojson --csv out.csv": LIBRARY,
    "geoloc library scan ~/library --data-dir D": LIBRARY,
    "geoloc library list ~/library --data-dir D": LIBRARY,
    "geoloc library decide ~/library ~/library/img_00001.jpg accept --data-dir D": LIBRARY,
    "geoloc library decide ~/library ~/library/img_00008.jpg move --lat 39.95041 --lon -75.19229 --data-dir D": LIBRARY,
    "geoloc library decide ~/library ~/library/img_00009.jpg reject --data-dir D": LIBRARY,
    "geoloc library write ~/library --data-dir D --dry-run": LIBRARY,
    "geoloc library write ~/library --data-dir D": LIBRARY,
    "geoloc library export ~/library --data-dir D --geojson accepted.geojson --gpx accepted.gpx": LIBRARY,
    "geoloc library undo ~/library --data-dir D": LIBRARY,
    "geoloc library write ~/library --data-dir D --in-file": LIBRARY,
}


def commands(text: str) -> list[str]:
    """The logical lines of the README's sh blocks: comments dropped, continuations joined (a trailing
    backslash, or an indented line under a synopsis)."""
    out: list[str] = []
    for block in re.findall(r"```sh\n(.*?)```", text, re.S):
        joining = False
        for raw in block.splitlines():
            line = re.sub(r"(^|\s+)#(\s.*)?$", "", raw).rstrip()
            if not line.strip():
                joining = False
                continue
            cont = line.endswith("\\")
            line = line.rstrip("\\").rstrip()
            if out and (joining or raw[:1] == " "):
                out[-1] += " " + line.strip()
            else:
                out.append(line.strip())
            joining = cont
    return out


def shortest(command: str) -> str:
    """A synopsis line without its optional parts (``[--top-k 10]``, nested ones included)."""
    while True:
        stripped = re.sub(r"\s*\[[^\[\]]*\]", "", command)
        if stripped == command:
            return re.sub(r"\s+", " ", command).strip()
        command = stripped


def _real_photos(folder: Path) -> dict[str, Path]:
    """The files the README's lines name, as real photos: none of them in the mini collection (whose
    captures are the index's first 16)."""
    names = {
        "photo.jpg": PENN / "photos" / "img_00006.jpg",  # a query row of the mini manifest: its db crops are stored
        "a.jpg": PENN / "crops" / "img_00017_4.jpg",
        "b.jpg": PENN / "crops" / "img_00018_4.jpg",
        "c.jpg": PENN / "crops" / "img_00021_4.jpg",
        "phone-photo-with-gps.jpg": PENN / "photos" / "img_00019.jpg",  # EXIF GPS
    }
    for name, src in names.items():
        shutil.copyfile(src, folder / name)
    return names


@pytest.fixture(scope="module")
def shell(tmp_path_factory, mini_collection, fitted_models, mini_manifest):
    """A served copy of the mini collection and a function running one README line in bash, as typed."""
    root = tmp_path_factory.mktemp("readme")
    data, work, home, curl_home = root / "data", root / "work", root / "home", root / "curl"
    shutil.copytree(mini_collection, data)
    for d in (work, home / "photos", curl_home):
        d.mkdir(parents=True)
    _real_photos(work)
    for n in (20, 33):  # `geoloc ingest ~/photos`: photos with EXIF GPS
        shutil.copyfile(PENN / "photos" / f"img_{n:05d}.jpg", home / "photos" / f"img_{n:05d}.jpg")
    rows = ["image,lat,lon,heading,captured_at,label"]
    for n, (lat, lon) in ((34, (39.9512, -75.1935)), (36, (39.9514, -75.1931))):
        shutil.copyfile(PENN / "crops" / f"img_{n:05d}_4.jpg", work / f"survey_{n}.jpg")
        rows.append(f"survey_{n}.jpg,{lat},{lon},90,2024-09-23T16:10:00,survey {n}")
    (work / "survey.csv").write_text("\n".join(rows) + "\n")
    # Every curl says its HTTP status on a last line, and fails loudly on a refused connection.
    (curl_home / ".curlrc").write_text('silent\nshow-error\nwrite-out = "\\nHTTP %{http_code}\\n"\n')
    venv_bin = str(REPO / ".venv" / "bin")
    path = os.pathsep.join(p for p in os.environ.get("PATH", "").split(os.pathsep) if p != venv_bin)
    server = Server(data, fitted_models)
    server.wait_ready()
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith(("GEOLOC_", "VIRTUAL_ENV"))},
        "PATH": path,
        "HOME": str(home),
        "CURL_HOME": str(curl_home),
        "GEOLOC_DATA_DIR": str(data),
        "GEOLOC_MODELS_DIR": str(fitted_models),
        "GEOLOC_CONFIG": CONFIG,
        "GEOLOC_SHARED_DIR": str(SHARED),
        "GEOLOC_ORT_THREADS": "1",
        "PYTHONUNBUFFERED": "1",
    }
    placeholders = {
        "http://127.0.0.1:8000": server.url,
        "/backups/": f"{root}/backups/",
        " D2": f" {root}/restored",
        " M ": f" {mini_manifest} ",
    }

    def run(line: str, job_id: str | None = None, ref_id: int | None = None) -> subprocess.CompletedProcess:
        for name, value in placeholders.items():
            line = line.replace(name, value)
        if job_id is not None:
            line = line.replace("JOB_ID", job_id)
        if ref_id is not None:
            line = line.replace("REF_ID", str(ref_id))
        script = f'set -eo pipefail\ncd "{REPO}"\n{ACTIVATE}\ncd "{work}"\nKEY=$(geoloc api-key)\n{line}\n'
        return subprocess.run(["bash", "-c", script], capture_output=True, text=True, env=env, timeout=600, cwd=work)

    run.env, run.work, run.data, run.root, run.server = env, work, data, root, server
    yield run
    server.stop()


def _status_and_body(p: subprocess.CompletedProcess) -> tuple[int, str]:
    body, _, status = p.stdout.rstrip().rpartition("\nHTTP ")
    return int(status), body


def test_the_set_up_line_is_in_the_readme_and_geoloc_needs_it(shell):
    assert f"```sh\n{ACTIVATE}" in README
    assert ACTIVATE in (REPO / "Makefile").read_text().split("\nrun:")[1].split("\n\n")[0], "make run must print it"
    bare = subprocess.run(
        ["bash", "-c", "command -v geoloc"], capture_output=True, text=True, env=shell.env, cwd=shell.work
    )
    assert bare.returncode != 0, "geoloc is on the PATH without activation: the test would prove nothing"
    p = shell("command -v geoloc && echo $KEY")
    assert p.returncode == 0 and p.stdout.splitlines()[0] == str(REPO / ".venv" / "bin" / "geoloc"), p.stderr
    assert p.stdout.splitlines()[1] == shell.server.api_key


def test_every_readme_command_is_run_here_or_elsewhere(shell):
    """The curl lines in order (a job id from an answer feeds the JOB_ID line, a reference it added the REF_ID
    lines), then the geoloc lines. The README edits and deletes only a reference it added itself, never one
    of the demo collection's (its PATCH and DELETE once named a demo reference)."""
    lines = [c for c in commands(DOCS) if c.split()[0] in ("curl", "geoloc")]
    curls = [c for c in lines if c.startswith("curl")]
    assert len(curls) >= 14, curls
    assert not [c for c in curls if re.search(r"/references/\d", c)], "a README line names a demo reference"
    before = {r["id"] for r in shell.server.client.get("/references", params={"limit": 500}).json()["items"]}
    job_id, ref_id = None, None
    answers: dict[str, str] = {}
    for line in curls:
        p = shell(line, job_id, ref_id)
        assert p.returncode == 0, (line, p.stdout, p.stderr)
        status, body = _status_and_body(p)
        assert 200 <= status < 300, (line, status, body)
        if "/references" in line and "-F image=" in line:
            assert status == 202, (line, body)
            job_id, ref_id = json.loads(body)["job_id"], json.loads(body)["reference_ids"][0]
        answers[line] = body
    assert ref_id not in before
    after = {r["id"] for r in shell.server.client.get("/references", params={"limit": 500}).json()["items"]}
    assert before <= after and ref_id not in after, "the README's DELETE removed the reference it added"
    located = json.loads(next(b for line, b in answers.items() if "/locate" in line))
    assert located["candidates"] and located["config"] == CONFIG
    assert json.loads(next(b for line, b in answers.items() if "JOB_ID" in line))["id"] == job_id
    assert (shell.work / "thumb.jpg").read_bytes()[:2] == b"\xff\xd8"
    assert json.loads(next(b for line, b in answers.items() if "-X PATCH" in line))["label"] == "College Hall"
    assert "geoloc_" in next(b for line, b in answers.items() if line.endswith("/metrics"))
    by_id = json.loads(next(b for line, b in answers.items() if "after=0" in line))
    assert by_id["items"] and by_id["total"] is None and "next_after" in by_id

    ran = []
    for line in (c for c in lines if c.startswith("geoloc")):
        if shortest(line) in ELSEWHERE or line in ELSEWHERE:
            continue
        p = shell(shortest(line))
        assert p.returncode == 0, (line, p.stdout[-2000:], p.stderr[-2000:])
        ran.append(shortest(line))
    assert {
        "geoloc check",
        "geoloc check --repair",
        "geoloc locate photo.jpg",
        "geoloc api-key",
        "geoloc datasets",
        "geoloc ingest ~/photos",
        "geoloc ingest survey.csv --workers 4",
        "geoloc ingest --manifest M --split db",
    } <= set(ran), ran
    assert (shell.root / "restored" / "references.sqlite").exists() and (shell.root / "backups").exists()
    refs = shell.server.client.get("/references", params={"limit": 500}).json()["items"]
    labels = {r["label"] for r in refs}
    assert {"survey 34", "survey 36", "img_00020.jpg", "img_00033.jpg"} <= labels, labels
    assert all(r["captured_at"] is None or "T" in r["captured_at"] for r in refs)
    unknown = [c for c in lines if c.startswith("geoloc") and shortest(c) not in ran and shortest(c) not in ELSEWHERE]
    assert not unknown, f"commands of README.md or docs/ run by no test: {unknown}"


def _shape(value):
    """The fields of an answer, recursively (a list by its first item's fields)."""
    if isinstance(value, dict):
        return {k: _shape(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_shape(value[0])] if value else []
    return None


def test_the_readme_example_answer_has_the_fields_of_a_real_one(shell):
    section = API_DOC.split("## A /locate answer, field by field", 1)[1].split("\n## ", 1)[0]
    example = json.loads(re.search(r"```json\n(.*?)```", section, re.S).group(1))
    p = shell("curl -F image=@photo.jpg -F top_k=3 http://127.0.0.1:8000/locate")
    status, body = _status_and_body(p)
    real = json.loads(body)
    assert status == 200, body
    # The stages timed differ by configuration (the README's is the default's, this server's hybrid-bin).
    assert "total" in example["timings_ms"] and "total" in real["timings_ms"]
    from app.api.schemas import EstimateOut

    # The README's answer is confident (the easy demo case): its estimate has exactly an estimate's fields,
    # and no reason; this server's answer may be either, so the rest is compared without the estimate.
    assert set(example["estimate"]) == set(EstimateOut.model_fields), example["estimate"]
    assert example["reason"] is None and example["reason_code"] is None
    assert _shape({**example, "timings_ms": {}, "estimate": None}) == _shape(
        {**real, "timings_ms": {}, "estimate": None}
    ), (example, real)
    for field in EstimateOut.model_fields:
        assert f"`{field}`" in section, field
    # Every field is defined in the table under the example.
    table = section.split("| field | what it is |", 1)[1]
    for field in [*example, *example["candidates"][0]]:
        assert f"`{field}`" in table or f"`.{field}`" in table or f"[].{field}`" in table, field


def test_the_readme_synopsis_shows_each_numeric_default_the_command_has():
    """`[--workers 2]` was once shown where the default is 1: every `[--option NUMBER]` of a synopsis
    line is the option's real default."""
    import typer.main

    from app.cli import app

    group = typer.main.get_command(app)
    checked = []
    for line in commands(DOCS):
        words = line.split()
        if words[0] != "geoloc" or len(words) < 2 or words[1] not in group.commands:
            continue
        params = {o: p for p in group.commands[words[1]].params for o in p.opts}
        for name, value in re.findall(r"\[(--[a-z-]+) (\d+(?:\.\d+)?)\]", line):
            if name in params and params[name].default is not None:  # None: the value is an example
                assert float(params[name].default) == float(value), (line, name, params[name].default)
                checked.append(f"{words[1]} {name}")
    assert "ingest --workers" in checked and "locate --top-k" in checked, checked


def test_the_readme_recipe_for_another_configuration_fills_its_data_dir_and_git_ignores_it():
    """The hybrid-bin recipe once served an empty collection (no ingest shown) from an untracked index-bin/: it
    ingests into the data dir it serves, and git ignores that folder."""
    text = " ".join(API_DOC.split())
    recipe = text.split("serve another one on its own data dir", 1)[1].split("geoloc serve", 1)[0]
    assert "make fit CONFIG=hybrid-bin" in recipe
    assert re.search(r"geoloc ingest [^`]*--config hybrid-bin --data-dir index-bin", recipe), recipe
    assert "GEOLOC_CONFIG=hybrid-bin GEOLOC_DATA_DIR=index-bin" in recipe
    ignored = subprocess.run(["git", "check-ignore", "-q", "index-bin/references.sqlite"], cwd=REPO)
    assert ignored.returncode == 0, "index-bin/ is not ignored by git"

"""The Docker image, built for real with buildah (no Docker engine here) and run with chroot isolation: every
registered model is in it, and its `geoloc serve` on an empty data volume fits on the mounted photos, says
so on /ready, becomes ready and locates (`make test-container`; marker ``container``, not in `make test`:
a cold build takes many minutes).

How, without Docker Hub (only package registries are reachable): the base image is made from Debian
packages with mmdebstrap (python3, python3-venv, nodejs, npm) and given to the Dockerfile as BASE and
WEB_BASE; the build itself is `buildah bud --isolation chroot` (no container runtime: podman's crun cannot
run in this sandbox), and the service runs with `buildah run --isolation chroot --network host`. The host's
CA bundle is bind-mounted into the build, for sandboxes whose registry traffic goes through a proxy.
Skipped, with the reason, where buildah or mmdebstrap is missing (`apt-get install buildah mmdebstrap`).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import httpx
import pytest

from app.engine.configs import DEFAULT_CONFIG
from app.engine.geo import haversine_m
from app.engine.imageio import load_image
from tests.conftest import PENN, REPO, SQUEEZENET_IR
from tools.server_process import free_port

pytestmark = [
    pytest.mark.container,
    pytest.mark.skipif(
        not (shutil.which("buildah") and shutil.which("mmdebstrap")),
        reason="needs buildah and mmdebstrap (Debian packages: apt-get install buildah mmdebstrap)",
    ),
]

BASE = "localhost/geoloc-base:bookworm"
IMAGE = "localhost/geoloc:container-test"
#: The base: Python for the service, npm for the web stage (Leaflet and Swagger UI from the npm registry).
BASE_PACKAGES = "python3,python3-venv,libgomp1,passwd,ca-certificates,nodejs,npm"
CA_BUNDLE = Path("/etc/ssl/certs/ca-certificates.crt")
PHOTOS = [f"img_{n:05d}.jpg" for n in range(8)]


def _run(args: list[str], timeout: float, log: Path) -> str:
    with log.open("a") as f:
        f.write(f"$ {' '.join(args)}\n")
        f.flush()
        proc = subprocess.run(args, stdout=subprocess.PIPE, stderr=f, text=True, timeout=timeout)
        f.write(proc.stdout)
    assert proc.returncode == 0, f"{' '.join(args)} failed ({proc.returncode}); see {log}:\n{log.read_text()[-3000:]}"
    return proc.stdout


def _image_exists(name: str) -> bool:
    return subprocess.run(["buildah", "inspect", "--type", "image", name], capture_output=True).returncode == 0


@pytest.fixture(scope="module")
def build_log(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("container") / "build.log"


@pytest.fixture(scope="module")
def base_image(tmp_path_factory, build_log) -> str:
    """The Debian base, made once per machine (kept in buildah's image store)."""
    if not _image_exists(BASE):
        tar = tmp_path_factory.mktemp("base") / "base.tar"
        _run(["mmdebstrap", "--variant=minbase", f"--include={BASE_PACKAGES}", "bookworm", str(tar)], 1800, build_log)
        ctr = _run(["buildah", "from", "scratch"], 60, build_log).strip()
        try:
            _run(["buildah", "add", ctr, str(tar), "/"], 600, build_log)
            _run(["buildah", "commit", "-q", ctr, BASE], 600, build_log)
        finally:
            subprocess.run(["buildah", "rm", ctr], capture_output=True)
    return BASE


@pytest.fixture(scope="module")
def image(base_image, build_log) -> str:
    """The repository's Dockerfile, built as `docker compose build` would (the weights build context)."""
    args = ["nice", "-n", "10", "buildah", "bud", "--isolation", "chroot", "--layers"]
    args += ["--build-arg", f"BASE={base_image}", "--build-arg", f"WEB_BASE={base_image}"]
    args += ["--build-context", f"weights={SQUEEZENET_IR}", "-t", IMAGE]
    if CA_BUNDLE.is_file():
        args += ["-v", f"{CA_BUNDLE}:{CA_BUNDLE}:ro"]
    t0 = time.monotonic()
    _run([*args, str(REPO)], 3600, build_log)
    print(f"image built in {time.monotonic() - t0:.0f} s")
    return IMAGE


@pytest.fixture()
def container(image):
    ctr = subprocess.run(["buildah", "from", image], capture_output=True, text=True, check=True).stdout.strip()
    yield ctr
    subprocess.run(["buildah", "rm", ctr], capture_output=True)


def test_image_holds_every_registered_model(container, build_log):
    """`geoloc models build` in the Dockerfile builds every entry of the registry (XFeat included)."""
    from app.engine.registry import builds

    listed = _run(["buildah", "run", "--isolation", "chroot", container, "--", "ls", "/app/models"], 120, build_log)
    for entry in builds().values():
        for name in entry.files:
            assert name in listed.split(), f"{name} ({entry.name}) is not in the image: {listed}"


def test_image_carries_exiftool(container, build_log):
    """`geoloc library write` writes GPS with exiftool: the image carries it."""
    out = _run(["buildah", "run", "--isolation", "chroot", container, "--", "exiftool", "-ver"], 120, build_log)
    assert float(out.strip()) >= 12, out


def test_image_dumps_the_compose_database_version(container, build_log):
    """`geoloc backup` on PostgreSQL runs pg_dump, which must be at least the server's major version: the
    image's client against the compose file's postgres image."""
    import re

    import yaml

    out = _run(["buildah", "run", "--isolation", "chroot", container, "--", "pg_dump", "--version"], 120, build_log)
    client = int(re.search(r"\(PostgreSQL\) (\d+)", out).group(1))
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    server = int(re.match(r"postgres:(\d+)", compose["services"]["postgres"]["image"]).group(1))
    assert client >= server, out


def test_container_first_start_then_locate(container, tmp_path):
    """The image's own CMD environment on an empty data volume and a mounted photo folder (as the compose
    file runs it): /health at once, /ready 503 with the first start's step, then ready, then /locate."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in PHOTOS:
        shutil.copy(PENN / "photos" / name, photos / name)
    data = tmp_path / "data"
    data.mkdir()
    os.chown(data, 10001, 10001)  # the image's geoloc user owns the volume, as Docker's named volume does
    port = free_port()
    log = (tmp_path / "container.log").open("w")
    proc = subprocess.Popen(
        ["buildah", "run", "--isolation", "chroot", "--network", "host",
         "-v", f"{photos}:/photos:ro", "-v", f"{data}:/data",
         "-e", "GEOLOC_INITIAL_PHOTOS=/photos", "-e", "GEOLOC_ORT_THREADS=1",
         container, "--", "geoloc", "serve", "--host", "127.0.0.1", "--port", str(port)],
        stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
    )  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    said: list[str] = []
    try:
        deadline = time.time() + 900
        ready = None
        with httpx.Client(base_url=url, timeout=30) as client:
            while time.time() < deadline and ready is None:
                assert proc.poll() is None, (tmp_path / "container.log").read_text()[-3000:]
                try:
                    health, r = client.get("/health"), client.get("/ready")
                except httpx.TransportError:
                    time.sleep(0.5)
                    continue
                assert health.status_code == 200
                if r.status_code == 200:
                    ready = r.json()
                else:
                    assert r.status_code == 503 and r.json()["error"] == "not_ready", r.text
                    if not said or said[-1] != r.json()["message"]:
                        said.append(r.json()["message"])
                    time.sleep(0.5)
            assert ready is not None, f"not ready; /ready said {said[-3:]}"
            assert ready["index_size"] == len(PHOTOS) and ready["config"] == DEFAULT_CONFIG, ready
            assert any(m.startswith("first start: fitting the pipeline: step 2 of 3") for m in said), said
            query = photos / PHOTOS[5]
            r = client.post("/locate", files={"image": query.read_bytes()}, data={"top_k": "3"})
            assert r.status_code == 200, r.text
            best = r.json()["candidates"][0]
            lat, lon = load_image(query.read_bytes()).gps
            assert haversine_m(lat, lon, best["lat"], best["lon"]) < 1.0
        assert (data / "pipelines" / f"{DEFAULT_CONFIG}-g0" / "pipeline.json").is_file()  # in the volume, not the image
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        log.close()

"""The Dockerfile and compose file checked statically (there is no Docker engine here); the image itself is
built with buildah and run by tests/test_container_build.py (`make test-container`)."""

import re
import shlex

import yaml

from tests.conftest import REPO

DOCKERFILE = (REPO / "Dockerfile").read_text()


def _instructions() -> list[tuple[str, str]]:
    text = re.sub(r"\\\n", " ", DOCKERFILE)
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            op, _, rest = line.partition(" ")
            out.append((op.upper(), rest.strip()))
    return out


def test_dockerfile_shape():
    ins = _instructions()
    ops = [op for op, _ in ins]
    final_from = [rest for op, rest in ins if op == "FROM"][-1]
    assert final_from == "${BASE}"  # python:3.11-slim by default; the container test gives a Debian-made one
    assert re.search(r"^ARG BASE=python:3\.1[1-9]-slim-[a-z]+$", DOCKERFILE, re.M)
    assert any(op == "COPY" and rest.startswith("--from=web") and "leaflet" in rest for op, rest in ins)
    swagger = next(rest for op, rest in ins if op == "COPY" and "swagger-ui-dist" in rest)  # /docs works offline
    assert "swagger-ui-bundle.js" in swagger and "swagger-ui.css" in swagger and "vendor/swagger-ui/" in swagger
    user = [rest for op, rest in ins if op == "USER"]
    assert user and user[-1] not in ("root", "0")
    assert ops.index("USER") > max(i for i, op in enumerate(ops) if op == "RUN")  # nothing runs as root after
    assert any(op == "COPY" and rest.startswith("--from=weights") for op, rest in ins)
    build = next(rest for op, rest in ins if op == "RUN" and "geoloc models build --from /tmp/weights" in rest)
    assert "--only" not in build and "geoloc models list --models-dir /app/models --check" in build  # checked after
    assert "HEALTHCHECK" in ops and "/ready" in DOCKERFILE
    cmd = next(rest for op, rest in ins if op == "CMD")
    assert "serve" in cmd and "0.0.0.0" in cmd
    for op, rest in ins:  # everything copied from the context exists
        if op == "COPY" and not rest.startswith("--from"):
            for src in shlex.split(rest)[:-1]:
                assert (REPO / src).exists(), src


def test_compose_shares_one_volume_and_checks_readiness():
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    api, worker = compose["services"]["api"], compose["services"]["worker"]
    assert "weights" in api["build"]["additional_contexts"]
    assert "/ready" in " ".join(api["healthcheck"]["test"])
    assert "--worker" in api["command"] and "none" in api["command"]  # the worker service encodes uploads
    assert worker["command"][:2] == ["geoloc", "worker"]
    vol = "geoloc-data"
    assert vol in compose["volumes"]
    assert f"{vol}:/data" in api["volumes"] and f"{vol}:/data" in worker["volumes"]
    assert worker["depends_on"]["api"]["condition"] == "service_healthy"


def test_every_service_of_the_image_builds_it_and_the_readme_names_its_first_pipeline():
    """No service names geoloc:latest without the build that makes it (compose would try to pull it from a
    registry that has none), and docs/operations.md names the folder the first start really writes."""
    from app.engine.configs import DEFAULT_CONFIG

    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    services = compose["services"]
    ours = {name: s for name, s in services.items() if s.get("image") == services["api"]["image"]}
    assert set(ours) >= {"api", "worker", "ray-head", "ray-worker", "api-replica"}
    for name, service in ours.items():
        assert service.get("build") == services["api"]["build"], name
    docs = "\n".join(p.read_text() for p in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))])
    assert f"/data/pipelines/{DEFAULT_CONFIG}-g0" in (REPO / "docs" / "operations.md").read_text()
    assert not re.search(r"/data/pipelines/(?!" + re.escape(DEFAULT_CONFIG) + r"-g0)", docs)


def test_compose_needs_no_python_on_the_host():
    """Nothing is mounted from a host build (no models/pipelines): the api fits an empty volume at its first
    start on the photos mounted at /photos, and the health check waits long enough for that fit."""
    text = (REPO / "docker-compose.yml").read_text()
    assert "models/pipelines" not in text
    compose = yaml.safe_load(text)
    api = compose["services"]["api"]
    assert api["environment"]["GEOLOC_INITIAL_PHOTOS"] == "${GEOLOC_INITIAL_PHOTOS:-/photos}"
    assert "${GEOLOC_PHOTOS:-../shared/data/penn-campus-gps/photos}:/photos:ro" in api["volumes"]
    assert api["healthcheck"]["start_period"].endswith("m")  # minutes, not the seconds of a plain load


def test_env_example_lists_every_setting_and_compose_reads_env():
    from app.settings import Settings

    example = (REPO / ".env.example").read_text()
    listed = set(re.findall(r"^# (GEOLOC_[A-Z_]+)=", example, re.M))
    assert {f"GEOLOC_{name.upper()}" for name in Settings.model_fields} <= listed
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    for service in compose["services"].values():
        assert {"path": ".env", "required": False} in service["env_file"]
    assert ".env" in (REPO / ".dockerignore").read_text().split()  # a key in .env never enters an image


def test_compose_ray_profile_runs_the_same_image():
    """The optional Ray cluster: head and scalable workers from the service's own image (Python and Ray
    versions match the driver), only under the ``ray`` profile, the head holding the data volume."""
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    services = compose["services"]
    head, worker = services["ray-head"], services["ray-worker"]
    image = services["api"]["image"]
    assert head["image"] == worker["image"] == image
    assert head["profiles"] == worker["profiles"] == ["ray"]
    assert "profiles" not in services["api"] and "profiles" not in services["worker"]  # `up` alone: no Ray
    assert head["command"][:3] == ["ray", "start", "--head"] and "--block" in head["command"]
    assert worker["command"][:2] == ["ray", "start"] and "--address=ray-head:6379" in worker["command"]
    assert "container_name" not in worker and "ports" not in worker  # --scale ray-worker=N must work
    assert "geoloc-data:/data" in head["volumes"]
    for service in (head, worker):  # one shared token, or the workers cannot join the head (Ray >= 2.5x)
        assert service["environment"]["RAY_AUTH_MODE"] == "token"
        assert service["environment"]["RAY_AUTH_TOKEN"] == "${RAY_AUTH_TOKEN:-}"
    assert "RAY_AUTH_TOKEN=" in (REPO / ".env.example").read_text()
    pinned = r'pip install -c constraints.txt ".[ray,postgres]"'  # the versions the suite ran (constraints.txt)
    assert any(pinned in rest for op, rest in _instructions() if op == "RUN")
    pyproject = (REPO / "pyproject.toml").read_text()
    assert re.search(r'^ray = \["ray\[data,client\]', pyproject, re.M)  # client: for ray:// addresses


def test_compose_postgres_profile_runs_a_database_and_a_replica_with_its_own_data_dir():
    """`--profile postgres`: the database and a second API on it, whose data dir is its own volume while the
    images are the primary's (mounted, and named by GEOLOC_IMAGES_DIR); `up` alone runs neither."""
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    services = compose["services"]
    db, replica = services["postgres"], services["api-replica"]
    assert db["profiles"] == replica["profiles"] == ["postgres"]
    assert db["image"].startswith("postgres:") and "pg_isready" in db["healthcheck"]["test"]
    assert replica["image"] == services["api"]["image"]
    assert "geoloc-replica:/data" in replica["volumes"] and "geoloc-data:/primary" in replica["volumes"]
    assert replica["environment"]["GEOLOC_IMAGES_DIR"] == "/primary/images"
    assert replica["environment"]["GEOLOC_SNAPSHOTS_DIR"] == "/primary"
    # the pipelines the primary's first start fits (and a refit adds) are the replica's too
    assert "ln -sfn /primary/pipelines /data/pipelines && exec geoloc serve" in replica["command"][-1]
    assert replica["depends_on"]["postgres"]["condition"] == "service_healthy"
    assert {"geoloc-replica", "geoloc-postgres"} <= set(compose["volumes"])


#: The major version of PostgreSQL's client (``postgresql-client``) in each Debian release.
DEBIAN_POSTGRES_CLIENT = {"bookworm": 15, "trixie": 17}


def test_image_can_dump_the_compose_database():
    """`geoloc backup` on PostgreSQL runs pg_dump, which refuses a server of a newer major version than its
    own: the image installs Debian's client, its base names the Debian release (which fixes the client's
    version), and the compose file's server is no newer than that client. The container test checks the
    built image's pg_dump (tests/test_container_build.py)."""
    install = next(rest for op, rest in _instructions() if op == "RUN" and "apt-get install" in rest)
    assert "postgresql-client" in install.split()
    release = re.search(r"^ARG BASE=python:3\.\d+-slim-([a-z]+)$", DOCKERFILE, re.M).group(1)
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    server = int(re.fullmatch(r"postgres:(\d+)(\.\d+)?(-\w+)?", compose["services"]["postgres"]["image"]).group(1))
    assert server <= DEBIAN_POSTGRES_CLIENT[release], (server, release)


def test_compose_milvus_profile_runs_milvus_standalone_and_an_api_on_it():
    """`--profile milvus`: Milvus standalone with its etcd and MinIO, and an API whose index is on it
    (GEOLOC_MILVUS_URI) with its own data dir; `up` alone runs none of them. The image has the client the
    milvus extra pins (read from pyproject.toml, not repeated)."""
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    services = compose["services"]
    names = ("milvus-etcd", "milvus-minio", "milvus", "api-milvus")
    assert all(services[n]["profiles"] == ["milvus"] for n in names)
    milvus, api = services["milvus"], services["api-milvus"]
    assert milvus["image"] == "milvusdb/milvus:v2.3.5" and milvus["command"] == ["milvus", "run", "standalone"]
    assert milvus["environment"]["ETCD_ENDPOINTS"] == "milvus-etcd:2379"
    assert milvus["environment"]["MINIO_ADDRESS"] == "milvus-minio:9000"
    assert api["image"] == services["api"]["image"]
    assert api["environment"]["GEOLOC_MILVUS_URI"] == "http://milvus:19530"
    assert api["depends_on"]["milvus"]["condition"] == "service_healthy"
    assert "geoloc-milvus-data:/data" in api["volumes"]
    pyproject = (REPO / "pyproject.toml").read_text()
    pin = re.search(r'^milvus = \["(pymilvus==[0-9.]+)", "milvus==[0-9.]+"\]', pyproject, re.M)
    assert pin and re.match(r"pymilvus==[0-9.]+$", pin.group(1))
    assert any("grep -o 'pymilvus==[0-9.]*' pyproject.toml" in rest for op, rest in _instructions() if op == "RUN")

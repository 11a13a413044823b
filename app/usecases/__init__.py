"""The application layer: one module per use case (locate, fit, accept uploads, operate a data dir, keep the
collection's index current, thumbnails), called alike by every face (HTTP in app/api, the CLI in app/cli.py,
evaluation and the benchmarks), so what the evaluation measures is what users get. Below it: app/engine
(recognition, numpy in and out), app/storage (SQL and files), app/jobs (background encoding and refits)."""

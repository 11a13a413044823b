"""Background jobs: the writer role (one per data dir), the ingestion worker, `geoloc ingest` and refit."""

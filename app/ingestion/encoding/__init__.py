"""Encoding: where the expensive step of ingestion runs. ``items`` (what is encoded and the one encode
path), ``local`` (the thread-pool engine, the bulk loop, ``make_engine``), ``ray`` (actors on a Ray
cluster, an optional extra)."""

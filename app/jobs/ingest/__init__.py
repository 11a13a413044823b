"""Bulk ingestion (`geoloc ingest SOURCE`): sources, the resumable run, its progress."""

"""Jobs over a whole data dir that are not the write path (``app.ingestion``): the re-fit and its
re-encoding, and the first start of an empty data dir."""

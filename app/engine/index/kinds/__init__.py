"""Index kinds, one module each, found by name (``app.engine.index.base.build_index``)."""

"""Search structures: ``vectors`` (one FAISS index, float or binary) and ``references`` (the pair a
collection searches, with tombstones and region filters)."""

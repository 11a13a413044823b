"""Search structures: ``base`` (the ``VectorIndex`` protocol and the registry of kinds), ``kinds`` (one
module per kind), ``faiss_index`` (what the FAISS kinds share) and ``references`` (the pair a collection
searches: float and binary codes, two-stage search)."""

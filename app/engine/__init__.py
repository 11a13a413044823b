"""The recognition engine: image -> features -> aggregation -> codes -> index -> candidates.

No HTTP in here. Each stage is a small module taking and returning numpy arrays; ``pipeline`` composes
them according to a named configuration from ``configs``.
"""

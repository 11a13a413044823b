"""Pretrained models as plug-ins: global models (a dense feature map a pipeline pools and samples) and
matchers (pairwise verification), each one module plus one registry entry (``registry.py``)."""

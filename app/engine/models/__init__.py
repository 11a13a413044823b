"""Pretrained models as plug-ins: global models (a dense feature map a pipeline pools and samples), learned
local extractors, and the networks matchers run. Each module registers what it provides and how to build its
files (``app.engine.registry`` imports every module here); nothing here imports its modules."""

"""Encoding: where the expensive step of ingestion runs. ``items`` (what is encoded and the one encode
path), ``local`` (the thread-pool engine, the bulk loop, ``make_engine``), ``ray`` (actors on a Ray
cluster, an optional extra)."""

from app.encoding.items import Encoded, EncodeItem, encode_item
from app.encoding.local import EncodeEngine, LocalEngine, batched, encode_and_complete, make_engine

__all__ = [
    "EncodeEngine",
    "EncodeItem",
    "Encoded",
    "LocalEngine",
    "batched",
    "encode_and_complete",
    "encode_item",
    "make_engine",
]

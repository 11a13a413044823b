"""Open a data directory with its fitted pipeline: the wiring shared by the CLI and the service."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.engine.imageio import ImageLimits, LoadedImage, load_image
from app.engine.locator import Locator
from app.engine.pipeline import Pipeline, load_pipeline
from app.engine.search import ReferenceIndex
from app.store import ReferenceStore


@dataclass
class Collection:
    pipeline: Pipeline
    store: ReferenceStore
    index: ReferenceIndex
    limits: ImageLimits

    @property
    def locator(self) -> Locator:
        return Locator(self.pipeline, self.index, self.store.positions)

    def decode(self, data: bytes) -> LoadedImage:
        return load_image(data, self.limits)

    def add_encoded(
        self,
        items: list[tuple[bytes, str, float, float, dict, np.ndarray | None, np.ndarray | None]],
        snapshot: bool = True,
    ) -> list[tuple[int, bool]]:
        """Store already-encoded references, add the new ones to the index, snapshot once."""
        out = []
        for data, ext, lat, lon, meta, fcode, bcode in items:
            ref_id, created = self.store.add(data, ext, lat, lon, fcode, bcode, **meta)
            if created:
                self.index.add(
                    np.array([ref_id], np.int64),
                    None if fcode is None else fcode[None],
                    None if bcode is None else bcode[None],
                )
            out.append((ref_id, created))
        if snapshot:
            self.store.save_snapshot(self.index, self.pipeline, self.store.version)
        return out

    def delete(self, ref_id: int) -> bool:
        if not self.store.delete(ref_id):
            return False
        self.index.remove([ref_id])
        self.store.save_snapshot(self.index, self.pipeline, self.store.version)
        return True


def open_collection(
    data_dir: Path, models_dir: Path, config: str | None, limits: ImageLimits | None = None
) -> Collection:
    """The data dir's own configuration wins over ``config``: its codes were made by that pipeline."""
    store = ReferenceStore(data_dir)
    name = store.get_meta("config") or config or "hybrid"
    pipeline = load_pipeline(models_dir, name)
    store.bind(pipeline)
    return Collection(pipeline, store, store.build_index(pipeline), limits or ImageLimits())

"""What ``geoloc check`` reads from the database (a backup's copy is the backend's ``dump``)."""

from __future__ import annotations

from dataclasses import dataclass

from app.storage.database import Part
from app.storage.generations import CODES


@dataclass(frozen=True)
class StoredRow:
    """A reference as a check sees it: its image file's name, status and codes of the generation in use."""

    id: int
    image: str  # the file name under images/
    status: str
    float_code: bytes | None
    binary_code: bytes | None


class Maintenance(Part):
    def holds_tables(self) -> bool:
        """False for an SQLite main file whose content is still in a ``-wal`` file that is not there."""
        return self.database.backend.holds_tables(self.database.db)

    def stored_rows(self) -> list[StoredRow]:
        """Every row (any status), with its codes of the generation in use."""
        rows = self.database.db.execute(
            f"SELECT r.id, r.sha256, r.image_ext, r.status, {CODES} FROM refs r "
            "LEFT JOIN switched_codes s ON s.ref_id = r.id"
        ).fetchall()
        return [StoredRow(i, f"{sha}.{ext}", status, f, b) for i, sha, ext, status, f, b in rows]

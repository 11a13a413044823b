"""The storage's settings, and the backend they name.

Why here and not only in ``app.settings``: ``Settings`` extends ``StorageSettings``, so each variable is
declared and read in one place, while the storage (which the rest of the app imports) never imports the
app's settings. The environment is read once, where a process starts (``Settings()`` at each entry point);
below it a backend is passed down, never looked up again: a process built from ``Settings(database_url=...)``
must not take SQLite's writer lock because no variable says PostgreSQL.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from app.storage.backend import StorageBackend


class StorageSettings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="GEOLOC_", env_file=None, extra="ignore")

    database_url: str | None = Field(
        None,
        description="postgresql://user@host:port/db: the rows on PostgreSQL, shared by several hosts (unset: "
        "SQLite in the data dir)",
    )
    images_dir: Path | None = Field(
        None, description="with PostgreSQL: the images folder every host mounts (unset: DATA_DIR/images)"
    )
    snapshots_dir: Path | None = Field(
        None,
        description="with PostgreSQL: where the index snapshots are written and loaded, a path every host "
        "mounts so a replica starting cold loads the writer's newest one (unset: the data dir)",
    )

    @field_validator("database_url", "images_dir", "snapshots_dir", mode="before")
    @classmethod
    def _blank_is_unset(cls, value):
        """An empty variable (``GEOLOC_DATABASE_URL=`` in a compose file) means unset, as it always did."""
        return None if isinstance(value, str) and not value.strip() else value

    @field_validator("database_url")
    @classmethod
    def _postgres_url(cls, url: str | None) -> str | None:
        if url is not None and url.strip().split(":", 1)[0] not in ("postgresql", "postgres"):
            raise ValueError(f"GEOLOC_DATABASE_URL must be a postgresql:// URL (or unset for SQLite), not {url!r}")
        return url.strip() if url else url

    def backend(self, data_dir: Path) -> StorageBackend:
        """The backend these settings name for ``data_dir``: PostgreSQL with ``database_url``, else SQLite in
        the data dir (where ``images_dir`` and ``snapshots_dir`` do not apply: one host)."""
        if self.database_url:
            from app.storage.postgres import PostgresBackend

            return PostgresBackend(self.database_url, data_dir, self.images_dir, self.snapshots_dir)
        from app.storage.sqlite import SqliteBackend

        return SqliteBackend(data_dir)

"""The storage backend: everything that differs between SQLite (the embedded default) and PostgreSQL
(several hosts on one collection), behind one interface, chosen once from ``Settings``.

Why one object: the store's parts (``store``, ``queue``, ``changes``, ``generations``, ``identity``,
``removals``, ``maintenance``) write one SQL (SQLite's spelling; the PostgreSQL backend's connection
translates it) and ask the backend for the rest: how a batch of rows is bulk-inserted, how other processes
learn of a commit, checkpoints, the id counters, the writer role's lock, dump and restore. A third backend
is one module implementing ``StorageBackend`` plus one line in ``StorageSettings.backend``
(``app.storage.settings``); nothing else branches on which backend runs.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from app.storage.errors import is_storage_error

if TYPE_CHECKING:
    from app.storage.integrity import DatabaseFiles


class WriterLock(Protocol):
    """The lock that makes one process the writer (the ingestion worker and the snapshots' author)."""

    can_be_lost: bool

    def acquire(self) -> bool: ...
    def alive(self) -> bool: ...
    def release(self) -> None: ...

    @property
    def held(self) -> bool: ...

    @property
    def where(self) -> str: ...


class Listener(Protocol):
    """A thread that calls back when another process commits an index change."""

    def start(self) -> Listener: ...
    def stop(self) -> None: ...


class StorageBackend(ABC):
    """Where the rows live and what only that engine does. ``name`` is what /health and backups report."""

    name: str
    #: Whether processes on several hosts share the rows, so every host must mount one images folder
    #: (``app.storage.shared_images`` checks it).
    hosts_share_images: bool = False
    #: The backend's raw error types (the API maps one that escapes ``storage_guard`` to a 503).
    exceptions: tuple[type[Exception], ...]

    def __init__(self, data_dir: Path, images_dir: Path, snapshots_dir: Path):
        self.data_dir = Path(data_dir)
        self.images_dir = Path(images_dir)
        self.snapshots_dir = Path(snapshots_dir)

    @staticmethod
    def unavailable(exc: BaseException) -> bool:
        """Whether ``exc`` is the storage's own failure (an unwritable folder, a full disk, a read-only, locked
        or unreachable database: ``app.storage.errors.is_storage_error``), which a caller may retry later.
        Here so that a face given the backend classifies what escapes without importing the storage."""
        return is_storage_error(exc)

    # -- the connection --------------------------------------------------------------------------------
    @abstractmethod
    def connect(self, read_only: bool) -> Any:
        """A connection speaking the subset of ``sqlite3.Connection`` the parts use (``execute``,
        ``executemany``, ``in_transaction``, ``close``); a writable open also makes the folders."""

    @abstractmethod
    def exists(self) -> bool:
        """Whether there is a database to open (a check or repair of nothing is refused)."""

    @abstractmethod
    def describe(self) -> str:
        """The database as a person names it in a message (a file path, a server)."""

    def integrity(self) -> DatabaseFiles | None:
        """The local database files a writer watches (``app.storage.integrity``); None: a server owns them."""
        return None

    @abstractmethod
    def holds_tables(self, db) -> bool:
        """Whether the database holds the store's tables (an SQLite main file without its ``-wal`` may not)."""

    # -- writing ----------------------------------------------------------------------------------------
    @abstractmethod
    def insert_refs(self, db, columns: Sequence[str], rows: Sequence[Sequence]) -> dict[str, tuple[int, str]]:
        """Inside a write transaction: insert ``rows`` into ``refs`` (``columns`` starts with ``sha256``),
        skipping a sha256 already stored or earlier in ``rows``; ids are handed out in the rows' order.
        Returns sha256 -> (id, status) of the rows created."""

    @abstractmethod
    def copy_rows(self, db, table: str, columns: Sequence[str], rows: Sequence[Sequence]) -> None:
        """Inside a write transaction: append ``rows`` to ``table`` (the bulk path)."""

    def after_bulk_insert(self, db, created: int, high_water: int) -> None:
        """After a committed bulk insert of ``created`` rows (ids up to ``high_water``), under the store's
        lock; nothing by default."""
        return None

    def notify(self, db) -> None:
        """Inside a write transaction that changes the index: wake the other processes at its commit. By
        default nothing: processes of one host catch up at their next search (they compare versions)."""
        return None

    def stream_rows(self, db, sql: str, chunk: int) -> Iterator[list[tuple]]:
        """The rows of one bulk read (every code: a cold start, a new generation) ``chunk`` at a time, as the
        engine produces them: never the whole result in memory at once. ``db`` is inside a read transaction.
        SQLite steps its statement (``fetchmany``)."""
        cursor = db.execute(sql)
        while rows := cursor.fetchmany(chunk):
            yield rows

    # -- durability and identity -------------------------------------------------------------------------
    def checkpoint(
        self, mode: str, timeout_s: float, files: DatabaseFiles | None, refuse: Callable[[str], None]
    ) -> tuple[int, int, int] | None:
        """Copy the log's committed pages into the main database file: (busy, frames, checkpointed), or None
        when there is no such step or it could not run; ``refuse(why)`` when it failed because ``files``
        are no longer the ones the process opened."""
        return None

    @abstractmethod
    def ref_high_water(self, db) -> int:
        """The largest reference id ever handed out (the id counter, or a larger row id)."""

    @abstractmethod
    def raise_counter(self, db, table: str, column: str, mark: int) -> None:
        """Inside a write transaction: the id counter of ``table``'s ``column`` never hands out ``mark`` or
        below again."""

    # -- processes and hosts ------------------------------------------------------------------------------
    @abstractmethod
    def writer_lock(self) -> WriterLock:
        """The lock whose holder is the one writer process of this collection."""

    def change_listener(self, on_change: Callable[[], object]) -> Listener | None:
        """A listener calling ``on_change`` as other processes commit index changes; None where processes
        catch up at their next search (they compare versions before each one)."""
        return None

    # -- backup ---------------------------------------------------------------------------------------
    #: The database's file name in a backup folder.
    backup_name: str

    @abstractmethod
    def dump(self, dest_dir: Path) -> list[str]:
        """Write a consistent copy of the database into ``dest_dir`` (others keep writing meanwhile) and
        return the image file names its rows name, of that same state."""

    @abstractmethod
    def restore(self, source_dir: Path) -> None:
        """Restore the copy ``dump`` wrote in ``source_dir`` into this (empty) database."""

"""Modes of what the service creates in a data dir: private to its user, whatever the umask.

Why: the data dir holds every uploaded photo, their positions and the API key; with the usual umask (022)
they were world-readable (0644 files, 0755 folders). What already exists keeps its mode (an operator may
have chosen it) and keeps working.
"""

from __future__ import annotations

import os
from pathlib import Path

PRIVATE_DIR = 0o700
PRIVATE_FILE = 0o600


def private_dir(path: Path, parents: bool = False) -> None:
    """Make ``path`` 0700 when this call creates it; an existing folder keeps its mode."""
    if path.is_dir():
        return
    try:
        path.mkdir(PRIVATE_DIR, parents=parents)
    except FileExistsError:
        return  # made by another process meanwhile
    os.chmod(path, PRIVATE_DIR)  # mkdir's mode is narrowed by the umask, never widened: set it exactly


def create_private_file(path: Path) -> None:
    """Create ``path`` empty and 0600 unless it exists. SQLite makes its ``-wal`` and ``-shm`` with the main
    file's mode, so creating the (empty, valid) database file first makes all three private."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, PRIVATE_FILE)
    except FileExistsError:
        return
    try:
        os.fchmod(fd, PRIVATE_FILE)
    finally:
        os.close(fd)


def private_tree(root: Path) -> None:
    """Make ``root`` and every folder under it 0700 and every file 0600 (links are left alone). For what a
    backup or a restore writes: ``shutil`` and SQLite's backup create files with the umask's mode (0644 under
    the usual 022), and a backup holds every photo, position and the API key."""
    os.chmod(root, PRIVATE_DIR)
    for folder, dirs, files in os.walk(root):
        for name in dirs:
            path = os.path.join(folder, name)
            if not os.path.islink(path):
                os.chmod(path, PRIVATE_DIR)
        for name in files:
            path = os.path.join(folder, name)
            if not os.path.islink(path):
                os.chmod(path, PRIVATE_FILE)

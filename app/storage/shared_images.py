"""On PostgreSQL, every host must read and write one images folder (``GEOLOC_IMAGES_DIR``): a check that
refuses to serve when it does not.

Why: the rows are shared through the database, the image files are not. Two servers with their own data
dirs on one database, the shared path left out, accepted uploads on the host without the writer role and
the writer never found their files: those uploads were never indexed on either host, and nothing said
why. So the first host to serve records an id in the database and in a marker file in its images
folder; a host whose images folder holds another id, or none, is not reading the same folder.
"""

from __future__ import annotations

import uuid

from app.errors import ServiceError
from app.storage.store import ReferenceStore

#: The meta key and the marker file (a dot file: `geoloc check` and the sweep pass over those).
META_KEY = "images_dir_id"
MARKER = ".geoloc-images-id"


class ImagesNotShared(ServiceError):
    """This host's images folder is not the one the other hosts on the database use."""

    code = "not_ready"


def check_images_shared(store: ReferenceStore) -> None:
    """Raise ``ImagesNotShared`` when ``store``'s backend is shared by hosts (PostgreSQL) and its images
    folder is not the one recorded in the database; record it when none is (the first host). A folder
    without a marker that holds the newest reference's image (a restore, or a folder shared before this
    check existed) is adopted."""
    if not store.backend.hosts_share_images or store.read_only:
        return
    marker = store.images_dir / MARKER
    mine = marker.read_text().strip() if marker.exists() else None
    recorded = store.get_meta(META_KEY)
    if recorded is None:
        mine = mine or uuid.uuid4().hex
        marker.write_text(mine + "\n")
        store.db.execute("INSERT INTO meta(key, value) VALUES(?, ?) ON CONFLICT(key) DO NOTHING", (META_KEY, mine))
        recorded = store.get_meta(META_KEY)
    if mine is None and _holds_newest_image(store):
        marker.write_text(recorded + "\n")
        mine = recorded
    if mine != recorded:
        raise ImagesNotShared(
            f"the images folder {store.images_dir} is not the one the other hosts on this database use: on "
            f"PostgreSQL every host must set GEOLOC_IMAGES_DIR to one shared folder (an NFS or other network "
            "path), or an upload accepted here is never found by the host that encodes it"
        )


def _holds_newest_image(store: ReferenceStore) -> bool:
    row = store.db.execute("SELECT sha256, image_ext FROM refs ORDER BY id DESC LIMIT 1").fetchone()
    return row is not None and store.image_path_for(row[0], row[1]).exists()

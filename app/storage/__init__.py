"""Storage: everything that reads or writes the rows, the image files and the journals, and the only code
that does.

``store`` (``ReferenceStore``: rows and images, composed of the parts below over one ``Database``),
``database`` (the connection, transactions, the meta table), ``queue`` (pending rows, claims, jobs),
``changes`` (the index's change log), ``generations`` (a re-fit's codes and its switch), ``identity``
(the database's id, checkpoints, what binds a snapshot to it), ``removals`` (image files to remove),
``maintenance`` (what check reads), ``migrations`` (the schema's versions, upgraded at a writable open),
``backend`` (what differs between SQLite and PostgreSQL, one interface), ``sqlite`` and ``postgres`` (the two
backends), ``settings`` (the variables that choose one), ``files`` (image files written atomically),
``errors`` (which failures are the storage's own), ``snapshots`` (FAISS snapshot files), ``orphans`` (image
files nothing owns), ``journal`` (the ingestion journal).
"""

"""The write path, in one package: accepting uploads (``uploads``: validated before anything is stored),
the queue's use (pending rows claimed, encoded, completed), encoding on threads or on Ray (``encoding``),
thumbnails and stored local features made from the same decode (``thumbnails``), the writer role and its
worker (``writer``, ``worker``), bulk ingestion from a folder or CSV (``sources``, ``bulk``) and the
stored features' back-fill (``backfill``). The read side (locate, listing, fitting, operations) is
``app.usecases``."""

"""The evaluation protocol (``evaluate``) and the data sets it reads (``datasets``: manifests)."""

"""The service's errors, each with its API code, and the codes of the engine's errors.

Why here and not in the HTTP layer: a use case raises the error it means (a re-fit with nothing to fit on,
a backup into a folder that is not empty), and the code a client sees is part of that meaning. The HTTP
layer (``app/api/errors.py``) only looks the code up, so it needs none of the modules that raise them,
and a new error is one class with its code, here. The codes themselves are the frozen list in
``app/api/errors.py`` (``ERRORS``); a test checks that every code used here is in it.
"""

from __future__ import annotations

from typing import ClassVar

from app.engine import errors as engine


class ServiceError(engine.GeolocError):
    """An error of the application layer; ``code`` is its API error code."""

    code: ClassVar[str] = "internal_error"


class InvalidRequest(ServiceError):
    """Parameters that cannot describe a request (an empty or inverted region, a bad heading...)."""

    code = "invalid_request"


class StorageUnavailable(ServiceError):
    """The data dir cannot be written or read right now (permissions, full disk, read-only database).
    Nothing already stored is lost; the same request can be retried once the storage is back."""

    code = "storage_unavailable"


class StaleReindex(ServiceError):
    """The re-index this process runs is no longer the data dir's target (another one took over)."""

    code = "not_ready"


class OperationRefused(ServiceError):
    """A backup or restore that would overwrite something, or read something that is not a backup."""

    code = "invalid_request"


class ManifestCannotBeEvaluated(ServiceError):
    """The manifest's splits and groups leave a fold with nothing to fit on, to index or to query."""

    code = "invalid_request"


class RefitError(ServiceError):
    """The re-fit cannot run as asked (nothing stored, a bank source without its photos...)."""

    code = "invalid_request"


class FitRefused(ServiceError):
    """A fit asked for something its configuration or its data cannot give (a bank without local
    features, a train-only bank without training photos, an unknown source or kind)."""

    code = "invalid_request"


def _name(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


#: The engine's exception classes to codes (the engine knows nothing of the API), by qualified name: the
#: modules that define some of them load FAISS or scikit-learn, which the storage and the CLI's light
#: commands never need (a test checks that every name is a class). A subclass maps like its nearest base.
ENGINE_CODES: dict[str, str] = {
    _name(engine.UnreadableImage): "unreadable_image",
    _name(engine.ImageTooSmall): "image_too_small",
    _name(engine.ImageBadShape): "image_shape",
    _name(engine.ImageTooLarge): "too_large",
    _name(engine.UnsupportedImageFormat): "unsupported_image_format",
    _name(engine.NoGpsInImage): "no_gps_in_image",
    _name(engine.InvalidPosition): "invalid_position",
    "app.engine.index.references.UnsupportedMode": "unsupported_mode",
    "app.engine.configs.UnknownConfig": "invalid_request",
    # A pipeline naming an index kind no module provides, or an IVF fitted before its quantizer was trained at
    # fit: the collection cannot be served until the kind is installed or the data dir is refitted.
    "app.engine.index.base.UnknownIndexKind": "not_ready",
    "app.engine.index.base.IndexNotTrained": "not_ready",
    # The index's server (GEOLOC_MILVUS_URI) unreachable or refusing: retry once it is back; nothing is lost.
    "app.engine.index.kinds.milvus.IndexUnavailable": "not_ready",
    "app.engine.index.kinds.milvus.SharedIndexNotSnapshotted": "not_ready",
    # A configuration naming a stored-features profile no module defines: like an unknown configuration.
    "app.engine.stored_profiles.UnknownProfile": "invalid_request",
    _name(engine.ModelNotReady): "not_ready",
    _name(engine.IncompatibleArtifact): "not_ready",
    _name(engine.ModelBuildError): "not_ready",
    "app.engine.training.svm_training.NothingToTrainOn": "invalid_request",  # fit/eval leaving nothing to fit
    # `geoloc models add`: a spec that cannot be read, a graph that does not run as its spec says, or a name
    # already taken (``ModelNameTaken``, a subclass): the input was refused and nothing was added.
    "app.engine.model_spec.SpecRefused": "invalid_request",
    "app.engine.model_add.ModelRefused": "invalid_request",
}


def code_of(exc: BaseException) -> str:
    """The API code of a service or engine error; ``internal_error`` for one nobody mapped (a bug)."""
    if isinstance(exc, ServiceError):
        return exc.code
    for cls in type(exc).__mro__:
        if (code := ENGINE_CODES.get(_name(cls))) is not None:
            return code
    return "internal_error"

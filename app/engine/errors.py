"""Domain errors of the engine. The HTTP layer maps them to status codes; the engine knows none."""


class GeolocError(Exception):
    """Base class: every error the engine raises on purpose."""


class UnreadableImage(GeolocError):
    """The bytes are not an image we can decode (empty, truncated, not an image, animated...)."""


class UnsupportedImageFormat(GeolocError):
    """A real image in a format we do not accept (e.g. HEIC without its plugin, GIF)."""


class ImageTooLarge(GeolocError):
    """Too many bytes or too many pixels: refused before decoding the pixels."""


class ImageTooSmall(GeolocError):
    """Too few pixels to describe a place."""


class ImageBadShape(GeolocError):
    """Too long and thin to describe a place (a strip, a banner): its long side is many times its short side."""


class NoGpsInImage(GeolocError):
    """A position was needed from EXIF and the photo has none."""


class InvalidPosition(GeolocError):
    """Latitude/longitude out of range or not finite."""


class ModelBuildError(GeolocError):
    """The pretrained weights could not be converted."""


class ModelNotReady(GeolocError):
    """A built model or a fitted pipeline is missing: run ``geoloc models build`` / ``geoloc fit``."""


class IncompatibleArtifact(GeolocError):
    """A saved artifact's manifest is of a kind or version this code does not understand."""

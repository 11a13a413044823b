"""geoloc: a visual geolocation service (find where a photo was taken from geotagged references)."""

__version__ = "0.1.0"

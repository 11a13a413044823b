"""A photo library geolocated against itself: the folder's photos with GPS become (or join) the
collection, its photos without GPS are located in bulk (``scan``), reviewed (``LibraryJournal`` decisions),
written back only once accepted (``writeback``, with exiftool) and exported for GIS (``exports``).

One use case per function, called alike by `geoloc library ...`, the /library routes and the page."""

"""Map and route files users already have, read (and routes written) at the station (sans-IO).

:mod:`brasidas.mapfiles.files` has the readers and writers (it loads Shapely: import it when a
file comes); this package's top holds only what a daemon needs before that.
"""

from brasidas.mapfiles.errors import MAX_FILE_BYTES, FileRefused

__all__ = ["MAX_FILE_BYTES", "FileRefused"]

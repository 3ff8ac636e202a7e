"""Recordings (issue 23): MCAP files on the platform, Foxglove channels shared with the station."""

import re

NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,200}\.mcap$")
"""A finished recording's name as listed and downloaded (the platform's writer and the
station's downloads alike): no path separators, no hidden files."""

SESSION_HEADER = "X-Brasidas-Session"
"""The HTTP header a recording download carries its session token in (the station sends it,
the platform reads it)."""

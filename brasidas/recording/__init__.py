"""Recordings (issue 23): MCAP files on the platform, Foxglove channels shared with the station."""

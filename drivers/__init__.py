"""I/O with the outside world (MAVLink, cameras, rangefinders); no algorithms here."""

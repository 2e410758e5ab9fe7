"""One root exception, one subclass per area (DESIGN.md section 7)."""


class CompanionError(Exception):
    """Root of every error this project raises on purpose."""


class ConfigError(CompanionError):
    """A configuration value is missing, unknown or invalid. The message names the key."""


class GeometryError(CompanionError):
    """Invalid geometric input (non-finite values, degenerate rotations, bad shapes)."""


class DatasetError(CompanionError):
    """A dataset folder is missing files or has malformed content."""


class SitlError(CompanionError):
    """The simulator was asked for something it cannot produce."""

"""One root exception, one subclass per area (docs/architecture.md, "Conventions")."""


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


class AutopilotError(CompanionError):
    """``companion autopilot check | configure`` (or its PX4 alias ``companion px4``) cannot do
    its job with the autopilot, PX4 or ArduPilot: no link or no heartbeat, a parameter that
    cannot be read or written, a vehicle that is armed."""


class UnreachableError(CompanionError):
    """A peer the command needs does not answer: no autopilot on the link, no service on the
    status socket. ``companion`` exits 3 for it (1 is for problems found)."""


class AutopilotUnreachableError(AutopilotError, UnreachableError):
    """No autopilot heartbeat on the link (or the link cannot be opened)."""


class CalibrationError(CompanionError):
    """``companion calibrate`` cannot work with its input (no images, no board found, a bad
    board spec or ranges file). The message says what to fix."""


class NotEnoughViewsError(CalibrationError):
    """Too few usable board views for a trustworthy intrinsic calibration."""


class BatchError(CompanionError):
    """``companion results | sweep`` cannot run a batch as asked: an executor that is not
    installed or not reachable, a task spec that cannot be run, a result from other code."""

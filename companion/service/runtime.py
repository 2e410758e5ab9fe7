"""What the service's parts share: the config, the clock, the counters, the stop flag and the
warnings (one ``Runtime``, made by ``Service`` and handed to every part).

Inputs: the frozen ``Config``. Outputs: ``ServiceStats`` (counters and recent timings the
status and the exit report read), ``Runtime.stop`` (the run ends: every loop ends at its next
turn), ``Runtime.warn`` (a warning logged, kept for the status and told to its listeners:
MQTT), ``Runtime.sleep`` (a wait that ends early on stop). The clock is ``Runtime.clock``
(monotonic [ns]; a test replaces it to replay time).

``AutopilotKind`` is who flies, from its HEARTBEAT: the service's parts branch on it (PX4's
time sync and rates, ArduPilot's EKF origin and ODOMETRY quality), never on a name.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from companion.config import Config
from companion.drivers.ardupilot import MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_PX4
from companion.redact import redact_text, url_secrets
from companion.types import PoseEstimate

log = logging.getLogger("companion.service")


def now_ns() -> int:
    """Our clock: monotonic [ns] (the camera's and the time sync's)."""
    return time.monotonic_ns()


class AutopilotKind(enum.Enum):
    """Who flies, from its HEARTBEAT.autopilot (MAV_AUTOPILOT); NONE before one is heard."""

    NONE = "none"
    PX4 = "PX4"
    ARDUPILOT = "ArduPilot"
    OTHER = "other"  # heard, neither of the two (its name is in ServiceStats.autopilot)

    @classmethod
    def from_heartbeat(cls, autopilot: int) -> AutopilotKind:
        """HEARTBEAT.autopilot (MAV_AUTOPILOT enum value) -> the kind."""
        if autopilot == MAV_AUTOPILOT_PX4:
            return cls.PX4
        if autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
            return cls.ARDUPILOT
        return cls.OTHER


@dataclass
class ServiceStats:
    """Counters and recent timings (the status and the exit report read them)."""

    started_ns: int = field(default_factory=now_ns)
    frames_in: int = 0
    frames_dropped: int = 0
    frames_rejected: int = 0  # refused by the frame check (frozen, dark, saturated, ...)
    frames_processed: int = 0
    published: int = 0
    not_published: int = 0  # processed frames without a pose (not tracking / no scale)
    stale: int = 0  # poses not sent because their frame was older than stale_frame_ms
    pipeline_errors: int = 0  # frames on which the pipeline raised (a bug: logged)
    ranges_in: int = 0
    ranges_rejected: int = 0
    ranges_rejected_by: dict[str, int] = field(default_factory=dict)  # reason -> count
    attitudes_in: int = 0
    attitudes_rejected: int = 0  # not finite or outside the Euler ranges
    imus_in: int = 0  # SCALED_IMU accelerometer samples taken (gravity for the VO)
    imus_rejected: int = 0  # not finite or beyond 16 g
    foreign_messages: int = 0  # from another system id than the configured autopilot's
    timesync_replies: int = 0
    stamped_at_send: int = 0  # poses sent as of their sending (PX4 stamping on arrival)
    last_reset_counter: int = 0
    autopilot_heartbeat_ns: int = 0
    autopilot_system_id: int = 0
    autopilot: str = ""  # who flies in words, from its HEARTBEAT: PX4, ArduPilot, ...
    autopilot_kind: AutopilotKind = AutopilotKind.NONE  # the same, for the code to branch on
    autopilot_armed: bool = False  # its HEARTBEAT's MAV_MODE_FLAG_SAFETY_ARMED
    rates_acknowledged: set[int] = field(default_factory=set)
    # refused (COMMAND_ACK not ACCEPTED): not asked again until the autopilot comes back
    rates_refused: set[int] = field(default_factory=set)
    latency_ms: deque[float] = field(default_factory=lambda: deque(maxlen=20000))
    process_ms: deque[float] = field(default_factory=lambda: deque(maxlen=20000))
    # a frame's whole turn on the worker: the pipeline, the send and the keyframe work after it
    cycle_ms: deque[float] = field(default_factory=lambda: deque(maxlen=20000))
    publish_times_ns: deque[int] = field(default_factory=lambda: deque(maxlen=20000))
    warnings: deque[str] = field(default_factory=lambda: deque(maxlen=20))
    sent: deque[PoseEstimate] = field(default_factory=lambda: deque(maxlen=200))  # last poses
    statustexts: deque[tuple[int, str]] = field(default_factory=lambda: deque(maxlen=50))


class Runtime:
    """The shared state of one service run (the event loop's; see app.py for the threads)."""

    def __init__(self, config: Config) -> None:
        o = config.service
        self.config = config
        self.clock: Callable[[], int] = now_ns  # monotonic [ns]
        self.stats = ServiceStats(started_ns=self.clock())
        self.stop_event = asyncio.Event()
        # what a warning must never show (a driver's error may quote the camera URL)
        self.secrets = [
            *url_secrets(o.camera_url),
            *url_secrets(o.mavlink_url),
            o.mqtt.password,
            config.web.token,
        ]
        self.warning_listeners: list[Callable[[str], None]] = []
        self.stop_listeners: list[Callable[[], None]] = []  # woken on stop (a waiting loop)

    @property
    def stopping(self) -> bool:
        """Whether the service is on its way out (every loop ends at its next turn)."""
        return self.stop_event.is_set()

    def stop(self) -> None:
        """End the run: every loop ends at its next turn (waiting ones are woken)."""
        self.stop_event.set()
        for listener in self.stop_listeners:
            listener()

    def warn(self, text: str) -> None:
        """A warning for the operator: redacted, logged, kept (the status shows the last
        ones) and told to every listener (MQTT's event topic)."""
        text = redact_text(text, self.secrets)
        log.warning(text)
        self.stats.warnings.append(text)
        for listener in self.warning_listeners:
            listener(text)

    async def sleep(self, seconds: float) -> None:
        """Wait ``seconds``, or less when the service stops meanwhile."""
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self.stop_event.wait(), seconds)

"""Options of the service, its links and its telemetry (composed into the config as [service]).

They sit beside `config.py`, below the service and the drivers that read them (docs/architecture.md:
the config is composed below everything that uses it)."""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass
from typing import Literal

from companion.errors import ConfigError
from companion.options import opt

MAX_PORT = 65535
MAX_BAUD = 12_000_000  # the fastest USB serial adapters; termios refuses more
MAX_KEEPALIVE_S = 65535  # MQTT's keepalive is a 16-bit number of seconds
TOPIC_FORBIDDEN = "+#\x00"  # MQTT wildcards and NUL: never in a topic we publish to
LINK_KINDS = ("udpin", "udpout", "tcp", "serial")


def check_link_number(url: str, key: str) -> None:
    """ConfigError naming ``key`` when the number at the end of a link URL cannot work: a
    port outside 1..65535 (udpin/udpout/tcp:HOST:PORT) or a baud rate outside 1..12,000,000
    (serial:DEVICE:BAUD, DEVICE:BAUD). The rest of the URL is the link's to parse."""
    kind, _, rest = url.partition(":")
    head, _, tail = url.rpartition(":")
    if not head or not tail.isdigit():
        return
    number = int(tail[:12]) if len(tail) <= 12 else MAX_BAUD + 1
    if kind in LINK_KINDS[:3] and rest and not 1 <= number <= MAX_PORT:
        raise ConfigError(f"{key}: port must be 1..{MAX_PORT}, got {tail[:20]} in {url[:80]!r}")
    if (kind == "serial" or url.startswith("/dev/")) and not 1 <= number <= MAX_BAUD:
        raise ConfigError(
            f"{key}: baud rate must be 1..{MAX_BAUD}, got {tail[:20]} in {url[:80]!r}"
        )


OutputName = Literal["vision_position_estimate", "odometry", "both"]
OdometryFrame = Literal["local_frd", "local_ned"]


@dataclass(frozen=True, slots=True)
class MqttOptions:
    """Fleet telemetry to an MQTT broker (aiomqtt): topics companion/<system_id>/..."""

    enabled: bool = opt(False, "publish status (1 Hz, retained), pose (10 Hz) and events")
    host: str = opt("127.0.0.1", "broker host")
    port: int = opt(1883, "broker port (8883 for TLS)", ge=1, le=65535)
    username: str = opt("", "user name (empty = none)")
    password: str = opt("", "password (never logged)", secret=True)
    tls: bool = opt(False, "connect with TLS")
    ca_file: str = opt("", "CA certificate file for TLS (empty = the system's)")
    topic_prefix: str = opt("companion", "first topic level")
    status_hz: float = opt(1.0, "status rate [Hz]", gt=0, le=10)
    pose_hz: float = opt(10.0, "pose rate [Hz]", gt=0, le=50)
    queue_size: int = opt(200, "messages kept while the broker is away (oldest dropped)", ge=1)
    keepalive_s: int = opt(
        10, "MQTT keepalive [s] (the broker sends the will after 1.5x)", ge=2, le=MAX_KEEPALIVE_S
    )

    def __post_init__(self) -> None:
        bad = sorted(set(self.topic_prefix) & set(TOPIC_FORBIDDEN))
        if bad or not self.topic_prefix or self.topic_prefix.startswith("$"):
            raise ConfigError(
                "topic_prefix: a topic level without the wildcards + and #, NUL or a leading $ "
                f"(the broker drops the connection), got {self.topic_prefix!r}"
            )
        if len(self.topic_prefix.encode()) > 1024:
            raise ConfigError("topic_prefix: longer than 1024 bytes")


@dataclass(frozen=True, slots=True)
class SigningOptions:
    """MAVLink 2 signing of the autopilot link (off while key_file is empty)."""

    key_file: str = opt("", "32-byte secret (raw or 64 hex digits), mode 0600; empty = off")
    require_signed: bool = opt(True, "refuse unsigned/badly signed frames (HEARTBEAT allowed)")
    link_id: int = opt(0, "our signing link id", ge=0, le=255)
    timestamp_file: str = opt(
        "",
        "where the last signing timestamp persists (empty: $STATE_DIRECTORY/"
        "signing_timestamp under systemd, else next to the key file)",
    )


@dataclass(frozen=True, slots=True)
class StatustextOptions:
    """STATUSTEXT to the ground station on every state change an operator must know
    (companion/service/statustext.py, docs/service.md "Messages to the ground station")."""

    enabled: bool = opt(True, "send STATUSTEXT (through the autopilot to the ground station)")
    prefix: str = opt("CMP: ", "put before every text (who is speaking); ASCII, <= 8 characters")
    key_interval_s: float = opt(
        2.0, "one message per subject (camera, VO, ...) at most this often [s]", ge=0, le=60
    )
    burst: int = opt(5, "messages at once at most (token bucket size)", ge=4, le=50)
    rate_hz: float = opt(1.0, "messages per second on average at most (bucket refill)", gt=0, le=10)

    def __post_init__(self) -> None:
        if len(self.prefix) > 8 or not all(" " <= c <= "~" for c in self.prefix):
            raise ConfigError(f"prefix: ASCII, at most 8 characters, got {self.prefix!r}")


@dataclass(frozen=True, slots=True)
class ArduPilotOptions:
    """What the service adds for ArduPilot (told apart from PX4 by its HEARTBEAT): the EKF
    origin EKF3 needs without GPS (drivers/ardupilot.py)."""

    set_origin: bool = opt(
        False,
        "send SET_GPS_GLOBAL_ORIGIN (every second until GLOBAL_POSITION_INT shows the EKF holds "
        "it): needed without GPS, where EKF3 has no origin of its own",
    )
    origin_lat_deg: float = opt(0.0, "EKF origin latitude [deg, WGS-84]", ge=-90, le=90)
    origin_lon_deg: float = opt(0.0, "EKF origin longitude [deg, WGS-84]", ge=-180, le=180)
    origin_alt_m: float = opt(0.0, "EKF origin altitude [m AMSL]", ge=-1000, le=10000)
    set_declination: bool = opt(
        False,
        "`autopilot configure` writes the site's magnetic declination to COMPASS_DEC (with "
        "COMPASS_AUTODEC 0): without GPS ArduPilot cannot look it up, and with a compass heading "
        "(EK3_SRC1_YAW 1) EKF3's north is magnetic north until it is set",
    )
    declination_deg: float = opt(
        0.0, "the site's magnetic declination [deg, east positive]", ge=-180, le=180
    )

    def __post_init__(self) -> None:
        if self.set_origin and self.origin_lat_deg == 0.0 and self.origin_lon_deg == 0.0:
            raise ConfigError(
                "origin_lat_deg, origin_lon_deg: set_origin needs the site's position (0, 0 is "
                "what GLOBAL_POSITION_INT reports without an origin)"
            )


@dataclass(frozen=True, slots=True)
class ServiceOptions:
    """Links, rates and what is sent to the autopilot."""

    mavlink_url: str = opt(
        "udpin:127.0.0.1:14540", "autopilot link: udpin/udpout/tcp:HOST:PORT or serial:DEV:BAUD"
    )
    mavlink_local_port: int = opt(
        0, "udpout: send from this UDP port (0 = any; fixed survives our restarts)", ge=0, le=65535
    )
    system_id: int = opt(1, "MAVLink system id (the autopilot's)", ge=1, le=255)
    component_id: int = opt(197, "our component id (197 = VISUAL_INERTIAL_ODOMETRY)", ge=1, le=255)
    camera_url: str = opt("sitl://127.0.0.1:5600", "camera: sitl://, folder:PATH, /dev/videoN, URL")
    output: OutputName = opt(
        "vision_position_estimate", "vision_position_estimate, odometry or both"
    )
    odometry_frame: OdometryFrame = opt(
        "local_frd",
        "ODOMETRY's frame_id: local_frd (any heading: PX4 aligns it to its own north; "
        "ArduPilot's only) or local_ned (our frame is north-aligned from the autopilot's "
        "heading: PX4 takes it as VISION_POSITION_ESTIMATE's NED, with our yaw on "
        "EKF2_EV_CTRL bit 3)",
    )
    odometry_centre_frames: int = opt(
        0,
        "ODOMETRY (output odometry/both) as the centre of the last N poses with their central "
        "velocity, stamped (N-1)/2 frames back (for EKF2_EV_CTRL bit 2); 0 = the newest pose "
        "with the velocity over the last 150 ms",
        ge=0,
        le=15,
    )
    odometry_velocity_sigma_m_s: float = opt(
        0.1,
        "ODOMETRY's velocity sigma per axis [m/s] (its velocity covariance: EKF2 takes it as "
        "each sample's noise, EKF2_EVV_NOISE as its floor)",
        gt=0,
        le=10,
    )
    distance_sensor_rate_hz: float = opt(
        50.0, "DISTANCE_SENSOR rate asked from the autopilot [Hz]", gt=0, le=1000
    )
    attitude_rate_hz: float = opt(
        50.0, "ATTITUDE rate asked from the autopilot [Hz]", gt=0, le=1000
    )
    imu_rate_hz: float = opt(
        50.0,
        "SCALED_IMU rate asked from a PX4 autopilot [Hz] (its accelerometer gives the VO "
        "gravity: vo.imu_gravity_window_s); 0 = not asked",
        ge=0,
        le=1000,
    )
    px4_timesync_rate_hz: float = opt(
        50.0,
        "TIMESYNC request rate asked from a PX4 autopilot [Hz]: PX4 converts our time stamps "
        "only after ~500 of our answers (10 s at 50 Hz, 50 s at its own 10 Hz); 0 = not asked",
        ge=0,
        le=100,
    )
    px4_stamp_at_send: bool = opt(
        True,
        "while a PX4 autopilot stamps our poses with their arrival (its time sync not "
        "converged, as modelled from its TIMESYNC requests: at the start and ~10 s after a "
        "jump of either clock), send each pose carried to its sending time along its velocity "
        "and stamped then; false: the exposure's stamp always",
    )
    timesync_rate_hz: float = opt(
        2.0, "our own TIMESYNC requests [Hz] once settled (10 Hz before)", gt=0, le=50
    )
    stale_frame_ms: float = opt(
        100.0, "stop publishing when the last good frame is older than this [ms]", gt=0
    )
    frame_wait_ms: float = opt(
        60.0,
        "a queued frame older than this (since its exposure) is skipped for a newer one [ms]",
        gt=0,
    )
    attitude_wait_s: float = opt(
        3.0,
        "the VO does not initialise before the autopilot's attitude is at hand (its heading is "
        "our frame's) until this long after the first frame; then it goes without, warned [s]",
        ge=0,
        le=60,
    )
    report_path: str = opt("", "write a JSON summary here on exit (empty = none)")
    state_dir: str = opt(
        "",
        "what survives a restart (the last reset_counter); empty: $STATE_DIRECTORY under "
        "systemd, else $XDG_STATE_HOME/companion, else ~/.local/state/companion",
    )
    mqtt: MqttOptions = opt(MqttOptions(), "MQTT fleet telemetry")
    signing: SigningOptions = opt(SigningOptions(), "MAVLink 2 signing of the autopilot link")
    ardupilot: ArduPilotOptions = opt(ArduPilotOptions(), "ArduPilot only: the EKF origin")
    statustext: StatustextOptions = opt(StatustextOptions(), "STATUSTEXT to the ground station")
    status_socket: str = opt(
        "",
        "Unix socket of `companion status` (empty: $RUNTIME_DIRECTORY/status.sock under systemd, "
        "i.e. /run/companion/status.sock, else $XDG_RUNTIME_DIR/companion.sock, else "
        "/tmp/companion-UID.sock; `companion status` looks in /run/companion first)",
    )

    def __post_init__(self) -> None:
        check_link_number(self.mavlink_url, "mavlink_url")
        if self.frame_wait_ms >= self.stale_frame_ms:
            raise ConfigError(
                f"frame_wait_ms: must be < stale_frame_ms ({self.stale_frame_ms}), "
                f"got {self.frame_wait_ms}"
            )


MIN_TOKEN_CHARS = 16  # a web token shorter than this is guessable over Wi-Fi
LOOPBACK_NAMES = ("localhost",)


GpsHandover = Literal["none", "px4", "ardupilot", "auto"]


@dataclass(frozen=True, slots=True)
class GpsOptions:
    """Our output in the autopilot's GPS-aided frame (companion/service/gps_frame.py,
    docs/gps.md): GPS_RAW_INT's verdict, the 4-DoF alignment of our track to the GPS fixes,
    held through a GPS loss and slewed back onto GPS (companion/frames/)."""

    align: bool = opt(
        False,
        "read GPS_RAW_INT / GPS_GLOBAL_ORIGIN and send our estimate in the autopilot's GPS "
        "frame (off: our own frame, as without GPS)",
    )
    handover: GpsHandover = opt(
        "none",
        "the autopilot's actions at a GPS loss and after the return: px4 (EKF2_GPS_CTRL 0, then "
        "px4_gps_ctrl), ardupilot (MAV_CMD_SET_EKF_SOURCE_SET 2, then 1), auto (by the "
        "HEARTBEAT), none",
    )
    align_height: bool = opt(
        False,
        "move our height onto GPS altitude too (off: z stays ours, the autopilot's height "
        "reference: EKF2_HGT_REF 3 is ours, ArduPilot's EK3_SRCn_POSZ the baro)",
    )
    px4_gps_ctrl: int = opt(7, "EKF2_GPS_CTRL written back after the return", ge=1, le=15)
    px4_loss_carry: bool = opt(
        True,
        "at a GPS loss (handover px4): our output takes on EKF2's lag behind it (its "
        "LOCAL_POSITION_NED against ours over the last 0.5 s), EKF2_GPS_CTRL 0 follows 0.3 s "
        "later so that EKF2's reset onto ours lands where it was, and the slew takes the lag "
        "out at slew_rate_m_s (off: EKF2_GPS_CTRL 0 at once, EKF2 steps by its lag)",
    )
    max_eph_m: float = opt(3.0, "a fix is good with eph <= this [m]", gt=0, le=100)
    min_satellites: int = opt(6, "... and at least this many satellites", ge=4, le=64)
    good_after_s: float = opt(3.0, "GPS good again after this long of good fixes [s]", ge=0, le=60)
    window_s: float = opt(20.0, "the alignment's window of pairs [s]", gt=1, le=300)
    min_window_s: float = opt(8.0, "pairs needed before a fit [s]", gt=0, le=300)
    max_rms_m: float = opt(1.0, "a fit is taken when GPS and our track agree within [m RMS]", gt=0)
    slew_rate_m_s: float = opt(
        0.1, "the output moves onto a new alignment at most [m/s]", gt=0, le=5
    )
    slew_rate_deg_s: float = opt(0.5, "... and turns at most [deg/s]", gt=0, le=30)
    max_return_offset_m: float = opt(
        30.0, "a return this far from the held alignment at the vehicle is refused [m]", gt=0
    )

    def __post_init__(self) -> None:
        if self.handover != "none" and not self.align:
            raise ConfigError(
                f"handover: {self.handover!r} acts at the GPS frame's loss and return: needs "
                "align = true"
            )
        if self.min_window_s > self.window_s:
            raise ConfigError(
                f"min_window_s: at most window_s ({self.window_s:g} s), got {self.min_window_s:g}"
            )


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or a name) is this machine only: 127.0.0.0/8, ::1 or
    ``localhost``. Any other name, ``0.0.0.0`` and ``::`` (every interface) are not."""
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True, slots=True)
class WebOptions:
    """The live page in a browser (companion/service/web.py; docs/service.md, "The live
    page"): the camera with its features and laser dots, the scale, the track, the health
    lines. Read-only: GET requests only, nothing of the service can be changed from it."""

    enabled: bool = opt(False, "serve the live page (costs nothing while nobody watches)")
    host: str = opt(
        "127.0.0.1",
        "address to listen on: loopback by default (an SSH tunnel); another address (the "
        "vehicle's Wi-Fi, 0.0.0.0) needs web.token",
    )
    port: int = opt(8080, "TCP port of the page", ge=1, le=MAX_PORT)
    token: str = opt(
        "",
        f"the page's password, asked on every request (?token= or the X-Companion-Token "
        f"header): required unless host is loopback; >= {MIN_TOKEN_CHARS} printable ASCII "
        "characters, no spaces",
        secret=True,
    )
    image_hz: float = opt(5.0, "camera images sent to a viewer per second at most", gt=0, le=10)
    image_width: int = opt(
        480, "images sent this wide [px] at most (smaller for phones; 0 = the camera's)", ge=0
    )
    jpeg_quality: int = opt(70, "JPEG quality of the images sent", ge=20, le=95)

    def __post_init__(self) -> None:
        if not self.host or any(c.isspace() for c in self.host):
            raise ConfigError(f"host: an address or a host name, got {self.host!r}")
        if self.token and (
            len(self.token) < MIN_TOKEN_CHARS or not all("!" <= c <= "~" for c in self.token)
        ):
            raise ConfigError(
                f"token: at least {MIN_TOKEN_CHARS} printable ASCII characters without spaces "
                f"(got {len(self.token)} characters)"
            )
        if self.enabled and not self.token and not is_loopback(self.host):
            raise ConfigError(
                f"token: required when host is not loopback (host = {self.host!r}: anyone on "
                'that network could watch); set web.token, or host = "127.0.0.1" and an SSH '
                "tunnel"
            )
        if 0 < self.image_width < 80:
            raise ConfigError(f"image_width: 0 (the camera's) or >= 80 px, got {self.image_width}")


def web_flag(text: str) -> dict[str, object]:
    """``companion run --web [HOST:]PORT`` as [web] keys (enabled, host, port); ConfigError
    naming ``--web`` when it is not that."""
    host, sep, port = text.rpartition(":")
    if not port.isdigit() or not 1 <= int(port[:6]) <= MAX_PORT or (sep and not host):
        raise ConfigError(f"--web: expected [HOST:]PORT with a port 1..{MAX_PORT}, got {text!r}")
    keys: dict[str, object] = {"enabled": True, "port": int(port)}
    if host:
        keys["host"] = host.strip("[]")
    return keys

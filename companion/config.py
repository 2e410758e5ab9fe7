"""Typed configuration: frozen dataclasses loaded from TOML, validated once at load.

Every option lives in exactly one dataclass field with a default and a one-line ``help``
(docs/architecture.md, "Conventions"). The loader walks the fields, so adding an option is one
line. A wrong type, a value outside its bounds or an unknown key raises :class:`ConfigError`
naming the key (``camera.fx: must be > 0, got -5.0``); the CLI turns that into exit code 2.

Frames: sensor mounts are given in the body frame (FRD) as a position ``xyz_m`` and ZYX angles
``rpy_deg`` of the sensor frame; a camera with ``rpy_deg = [0, 0, 90]`` looks down with the image
top towards the nose (docs/architecture.md, "Frames, units, names"). A range sensor's beam is +z
of its own frame.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np

from companion.attitude.options import AttitudeOptions
from companion.dpose.options import DposeOptions
from companion.errors import ConfigError
from companion.geometry import se3
from companion.geometry.camera import CameraModel
from companion.geometry.lens_check import lens_problem
from companion.options import opt
from companion.redact import redact_url
from companion.render_options import RenderConfig as RenderConfig
from companion.scale.options import ScaleOptions
from companion.service_options import GpsOptions, ServiceOptions, WebOptions, check_link_number
from companion.sitl_options import DeliveryFaults, GroundOptions, RangeEffects
from companion.toml_files import merge, read_config_toml
from companion.types import F64, RangeSensorSpec
from companion.vo.options import VoOptions


@dataclass(frozen=True, slots=True)
class MountConfig:
    """Pose of a sensor frame in the body frame (FRD)."""

    xyz_m: tuple[float, float, float] = opt((0.0, 0.0, 0.0), "sensor origin in the body frame [m]")
    rpy_deg: tuple[float, float, float] = opt(
        (0.0, 0.0, 0.0), "ZYX roll, pitch, yaw of the sensor frame in the body frame [deg]"
    )

    def T_body_sensor(self) -> F64:
        """(4, 4) transform sensor -> body."""
        return se3.from_xyz_rpy(self.xyz_m, np.radians(self.rpy_deg))


@dataclass(frozen=True, slots=True)
class CameraConfig:
    """The downward colour camera: intrinsics, distortion, rate and mount (T_body_cam)."""

    width: int = opt(640, "image width [px]", ge=16, le=8192)
    height: int = opt(480, "image height [px]", ge=16, le=8192)
    fx: float = opt(460.0, "focal length x [px]", gt=0)
    fy: float = opt(460.0, "focal length y [px]", gt=0)
    cx: float = opt(319.5, "principal point x [px]")
    cy: float = opt(239.5, "principal point y [px]")
    dist: tuple[float, float, float, float, float] = opt(
        (-0.12, 0.05, 0.0005, -0.0003, 0.0), "distortion k1 k2 p1 p2 k3 (OpenCV)"
    )
    rate_hz: float = opt(
        30.0, "frame rate [Hz] (asked of V4L2 and picamera2 cameras)", gt=0, le=1000
    )
    fourcc: str = opt(
        "",
        "V4L2 pixel format asked of a /dev/video camera, 4 characters (MJPG, YUYV); '' = its own",
    )
    exposure_us: float = opt(
        0.0, "fixed exposure time [us] (V4L2, picamera2); 0 = the camera's automatic", ge=0, le=1e6
    )
    readout_ms: float = opt(
        0.0,
        "rolling shutter: the time to read the rows out, top to bottom [ms] (CSI/UVC sensors "
        "10-30 ms, the sensor's datasheet); 0 = a global shutter",
        ge=0,
        le=200,
    )
    mount: MountConfig = opt(
        MountConfig(xyz_m=(0.05, 0.0, 0.08), rpy_deg=(0.0, 0.0, 90.0)),
        "T_body_cam: camera frame in the body frame",
    )

    def __post_init__(self) -> None:
        ok = len(self.fourcc) == 4 and all(c.isascii() and c.isprintable() for c in self.fourcc)
        if self.fourcc and not ok:
            raise ConfigError(f"fourcc: 4 ASCII characters (MJPG, YUYV) or '', got {self.fourcc!r}")
        problem = lens_problem(self.model())
        if problem is not None:
            raise ConfigError(
                f"dist: the lens model (k1 k2 p1 p2 k3 = {list(self.dist)} with fx fy cx cy = "
                f"{self.fx:g} {self.fy:g} {self.cx:g} {self.cy:g}) does not invert over the "
                f"{self.width} x {self.height} image: {problem}"
            )

    def model(self) -> CameraModel:
        """The camera model of these intrinsics."""
        k1, k2, p1, p2, k3 = self.dist
        return CameraModel(
            self.width, self.height, self.fx, self.fy, self.cx, self.cy, k1, k2, p1, p2, k3
        )

    def T_body_cam(self) -> F64:
        """(4, 4) camera -> body."""
        return self.mount.T_body_sensor()

    @property
    def readout_s(self) -> float:
        """The rolling shutter's readout time [s] (0: a global shutter)."""
        return self.readout_ms * 1e-3


@dataclass(frozen=True, slots=True)
class RangefinderConfig:
    """One downward distance sensor. Noise and fault fields are used by the simulator."""

    sensor_id: int = opt(0, "DISTANCE_SENSOR id (instance) of this sensor", ge=0, le=255)
    mount: MountConfig = opt(MountConfig(), "T_body_rf: sensor frame in the body frame (beam = +z)")
    min_m: float = opt(0.1, "minimum valid distance [m]", ge=0)
    max_m: float = opt(40.0, "maximum valid distance [m]", gt=0)
    sigma_a_m: float = opt(0.01, "noise sigma = a + b * range: constant part a [m]", ge=0)
    sigma_b: float = opt(0.0, "noise sigma = a + b * range: proportional part b", ge=0, le=1)
    rate_hz: float = opt(50.0, "measurement rate [Hz]", gt=0, le=1000)
    dropout_prob: float = opt(0.0, "probability that a reading is missing (SITL)", ge=0, le=1)
    outlier_prob: float = opt(0.0, "probability of a gross outlier reading (SITL)", ge=0, le=1)
    serial: str = opt(
        "", "a TFmini on the companion: DEVICE or DEVICE:BAUD (empty: DISTANCE_SENSOR from PX4)"
    )

    def __post_init__(self) -> None:
        if self.serial:  # DEVICE:BAUD: a baud rate termios takes
            check_link_number(f"serial:{self.serial}", "serial")
        if self.max_m <= self.min_m:
            raise ConfigError(f"max_m: must be > min_m ({self.min_m}), got {self.max_m}")

    def spec(self) -> RangeSensorSpec:
        """The calibration record handed to the algorithms."""
        return RangeSensorSpec(
            self.sensor_id,
            self.mount.T_body_sensor(),
            self.min_m,
            self.max_m,
            self.sigma_a_m,
            self.sigma_b,
        )


def _outward(sensor_id: int, x: float, y: float, tilt_deg: float = 4.0) -> RangefinderConfig:
    """A downward sensor at (x, y, 0.06) in the body, its beam tilted tilt_deg away from centre."""
    r = math.hypot(x, y)
    pitch = tilt_deg * x / r  # beam towards +x for pitch > 0
    roll = -tilt_deg * y / r  # beam towards +y for roll < 0
    return RangefinderConfig(
        sensor_id=sensor_id,
        mount=MountConfig(xyz_m=(x, y, 0.06), rpy_deg=(round(roll, 3), round(pitch, 3), 0.0)),
    )


# Four downward sensors in an asymmetric quadrilateral, sides 0.33-0.42 m, diagonals ~0.5 m.
DEFAULT_RANGEFINDERS: tuple[RangefinderConfig, ...] = (
    _outward(0, 0.25, 0.10),
    _outward(1, -0.08, 0.27),
    _outward(2, -0.24, -0.12),
    _outward(3, 0.12, -0.20),
)

# Six sensors for the number-of-sensors study (the default four plus two).
STUDY_RANGEFINDERS: tuple[RangefinderConfig, ...] = (
    *DEFAULT_RANGEFINDERS,
    _outward(4, 0.02, 0.32),
    _outward(5, -0.04, -0.30),
)


def triangle_rangefinders(spacing_m: float, sigma_m: float = 0.01) -> tuple[RangefinderConfig, ...]:
    """Three vertical sensors (ids 0-2) on an equilateral triangle of side spacing_m [m] centred
    under the body origin (the roll/pitch studies), noise sigma_m [m]."""
    rho = spacing_m / math.sqrt(3.0)
    return tuple(
        RangefinderConfig(
            sensor_id=k,
            mount=MountConfig(
                xyz_m=(
                    round(rho * math.cos(math.radians(90 + 120 * k)), 6),
                    round(rho * math.sin(math.radians(90 + 120 * k)), 6),
                    0.06,
                )
            ),
            sigma_a_m=sigma_m,
        )
        for k in range(3)
    )


def dpose_rangefinders(sigma_m: float = 0.01) -> tuple[RangefinderConfig, ...]:
    """The four d-Pose lasers (ids 0-3): distance sensors that also leave marks, their beams
    along companion.dpose.pattern.DPOSE_BEAMS (tilt = pitch of the mount, azimuth = yaw),
    5 cm apart around the body origin."""
    from companion.dpose.pattern import DPOSE_BEAMS

    out = []
    for k, (tilt_deg, az_deg) in enumerate(DPOSE_BEAMS):
        a = math.radians(az_deg)
        xyz = (round(0.05 * math.cos(a), 4), round(0.05 * math.sin(a), 4), 0.06)
        out.append(
            RangefinderConfig(
                sensor_id=k,
                mount=MountConfig(xyz_m=xyz, rpy_deg=(0.0, tilt_deg, az_deg)),
                sigma_a_m=sigma_m,
            )
        )
    return tuple(out)


TerrainName = Literal["flat", "hills", "urban", "slope"]
TrajectoryName = Literal[
    "hover", "circle", "lawnmower", "figure8", "climb", "spiral", "pad", "bob", "handheld"
]


@dataclass(frozen=True, slots=True)
class SitlConfig:
    """The simulated world and flight."""

    terrain: TerrainName = opt("hills", "terrain: flat, hills, urban or slope")
    trajectory: TrajectoryName = opt(
        "lawnmower",
        "hover, circle, lawnmower, figure8, climb, spiral, pad, bob (low indoors, up and down) "
        "or handheld (a camera turned by hand: not a multirotor's attitude)",
    )
    seed: int = opt(1, "seed of terrain, noise and faults", ge=0)
    seconds: float = opt(60.0, "flight duration [s]", gt=0, le=36000)
    altitude_m: float = opt(
        0.0, "height above ground [m]; 0 = terrain default (6, urban 12)", ge=0, le=200
    )
    speed_m_s: float = opt(3.0, "cruise speed [m/s] (multirotors cruise at 5-12)", gt=0, le=12)
    takeoff_landing: bool = opt(False, "start on the ground, take off, and land at the end")
    world_size_m: float = opt(160.0, "side of the square world [m]", ge=20, le=2000)
    height_resolution_m: float = opt(0.05, "height-map cell size [m]", gt=0, le=0.05)
    render: RenderConfig = opt(RenderConfig(), "camera rendering")
    ground: GroundOptions = opt(GroundOptions(), "the ground's surface and what moves on it")
    rangefinder: RangeEffects = opt(RangeEffects(), "the distance sensors' real-world faults")
    delivery: DeliveryFaults = opt(DeliveryFaults(), "how the camera delivers its frames")


RecordImageFormat = Literal["png", "jpg"]
RecordFormat = Literal["mcap", "folder"]
RecordImage = Literal["auto", "colour", "grey"]


@dataclass(frozen=True, slots=True)
class RecordOptions:
    """The flight recorder (companion/service/recorder.py): what the pipeline was fed, written
    as a dataset (docs/dataset.md) that ``companion eval DIR`` replays."""

    dir: str = opt(
        "",
        "record here (empty = off): mcap: the file DIR.mcap, folder: the folder DIR; "
        "{start} = the start time YYYYmmdd-HHMMSS",
    )
    format: RecordFormat = opt(
        "mcap", "mcap (one file; Foxglove, PlotJuggler) or folder (our CSV + image files)"
    )
    image: RecordImage = opt(
        "auto",
        "mcap: grey (a third of the size; the replay stays exact, the VO reads grey), colour, "
        "or auto (grey unless d-Pose, which reads colour, is on)",
    )
    max_mb: float = opt(2000.0, "disk budget of one recording [MB]; recording stops there", gt=0)
    min_free_mb: float = opt(200.0, "stop recording when the disk has less free [MB]", ge=0)
    image_format: RecordImageFormat = opt(
        "png", "png (lossless: the replay is exact) or jpg (about 5x smaller, replay approximate)"
    )
    png_compression: int = opt(
        1, "PNG: 0 stored, 1 fast (Sub filter, Huffman only), 2..9 zlib (slower)", ge=0, le=9
    )
    jpg_quality: int = opt(95, "JPEG quality", ge=50, le=100)
    queue_frames: int = opt(
        60, "frames waiting for the disk at most; a fuller queue stops the recording", ge=2
    )


@dataclass(frozen=True, slots=True)
class Config:
    """The whole configuration."""

    camera: CameraConfig = opt(CameraConfig(), "the downward colour camera")
    rangefinders: tuple[RangefinderConfig, ...] = opt(
        DEFAULT_RANGEFINDERS, "the downward distance sensors ([[rangefinders]] tables)"
    )
    vo: VoOptions = opt(VoOptions(), "visual odometry")
    scale: ScaleOptions = opt(ScaleOptions(), "metric scale")
    attitude: AttitudeOptions = opt(AttitudeOptions(), "roll/pitch from the distance sensors")
    dpose: DposeOptions = opt(DposeOptions(), "d-Pose in the published pose")
    service: ServiceOptions = opt(ServiceOptions(), "the service: links and output")
    web: WebOptions = opt(WebOptions(), "the live page in a browser ([web])")
    gps: GpsOptions = opt(GpsOptions(), "GPS in, GPS out: our output in its frame ([gps])")
    sitl: SitlConfig = opt(SitlConfig(), "the simulator")
    record: RecordOptions = opt(RecordOptions(), "the flight recorder ([record])")

    def __post_init__(self) -> None:
        ids = [r.sensor_id for r in self.rangefinders]
        if len(ids) != len(set(ids)):
            raise ConfigError(f"rangefinders: sensor_id values must be unique, got {ids}")
        chosen = self.attitude.sensor_ids
        unknown = sorted(set(chosen) - set(ids))
        if unknown:
            raise ConfigError(f"attitude.sensor_ids: no rangefinder with id {unknown}")
        if chosen and len(set(chosen)) < 3:
            raise ConfigError(
                f"attitude.sensor_ids: 3 different sensors needed, got {list(chosen)}"
            )
        lens = self.sitl.render.lens_error.problem(self.camera.model())
        if lens is not None:
            raise ConfigError(f"sitl.render.lens_error: the rendered lens {lens}")

    def oldest_stamp_ms(self) -> float:
        """How old our samples' stamps can be when they leave [ms]: a pose is dropped past
        service.stale_frame_ms, and ODOMETRY centred on N poses is stamped (N - 1) / 2 frames
        further back (companion/service/app.py holds its messages to this; `companion px4
        check` compares it with EKF2's horizon)."""
        o = self.service
        oldest = o.stale_frame_ms
        if o.output in ("odometry", "both") and o.odometry_centre_frames > 1:
            oldest += (o.odometry_centre_frames - 1) / 2 * 1000.0 / self.camera.rate_hz
        return oldest


# --------------------------------------------------------------------------- loading

T = TypeVar("T")
log = logging.getLogger(__name__)


def _short(value: Any, limit: int = 60) -> str:
    """repr(value), cut to ``limit`` characters (a 400-digit number is not worth printing)."""
    try:
        text = repr(value)
    except ValueError:  # an int beyond Python's printable digits
        return "a number too long to print"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(tp: Any, value: Any, key: str) -> Any:
    """Convert a TOML value to the annotated type, or raise ConfigError naming key."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a table, got {_short(value)}")
        return from_dict(typing.cast(type, tp), value, f"{key}.")
    if origin is Literal:
        if value not in args:
            raise ConfigError(f"{key}: must be one of {list(args)}, got {_short(value)}")
        return value
    if origin is tuple:
        if not isinstance(value, list):
            raise ConfigError(f"{key}: expected an array, got {_short(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{key}: expected {len(args)} values, got {len(value)}")
        pairs = enumerate(zip(args, value, strict=True))
        return tuple(_convert(a, v, f"{key}[{i}]") for i, (a, v) in pairs)
    if origin in (typing.Union, types.UnionType):
        raise ConfigError(f"{key}: union types are not supported in config")  # pragma: no cover
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {_short(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {_short(value)}")
        if abs(value) >= 2**63:
            raise ConfigError(f"{key}: integer out of range, got {_short(value)}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {_short(value)}")
        if isinstance(value, int) and abs(value) >= 2**63:
            raise ConfigError(f"{key}: number out of range, got {_short(value)}")
        if not math.isfinite(value):
            raise ConfigError(f"{key}: must be finite, got {_short(value)}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {_short(value)}")
        if "\x00" in value:  # no path, URL or name holds one; the OS refuses it in a path
            raise ConfigError(f"{key}: a NUL byte in the text, got {_short(value)}")
        return value
    raise ConfigError(f"{key}: unsupported type {_type_name(tp)}")  # pragma: no cover


def _check_bounds(f: dataclasses.Field[Any], value: Any, key: str) -> None:
    values = value if isinstance(value, tuple) else (value,)
    for v in values:
        if not isinstance(v, (int, float)) or isinstance(v, bool):
            continue
        for name, op, text in (
            ("ge", float.__ge__, ">="),
            ("gt", float.__gt__, ">"),
            ("le", float.__le__, "<="),
            ("lt", float.__lt__, "<"),
        ):
            if name in f.metadata and not op(float(v), float(f.metadata[name])):
                raise ConfigError(f"{key}: must be {text} {f.metadata[name]}, got {v!r}")


# Options that were removed: a config (or a recording's copy of the config it ran with) that
# still sets one loads, with a warning, instead of failing as an unknown key would
RETIRED_KEYS = {
    "dpose.blend": "the d-Pose offset's gain comes from dpose.vo_drift_per_m and _m_per_s",
}


def from_dict(cls: type[T], data: dict[str, Any], prefix: str = "") -> T:
    """Build dataclass ``cls`` from a TOML table; unknown keys and bad values raise ConfigError."""
    assert dataclasses.is_dataclass(cls)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for k in data:
        if k not in fields and f"{prefix}{k}" in RETIRED_KEYS:
            log.warning("%s%s: no longer used (%s); ignored", prefix, k, RETIRED_KEYS[prefix + k])
        elif k not in fields:
            known = ", ".join(sorted(fields))
            raise ConfigError(f"{prefix}{k}: unknown key (known: {known})")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        if name not in data:
            continue
        key = f"{prefix}{name}"
        value = _convert(hints[name], data[name], key)
        _check_bounds(f, value, key)
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except ConfigError as e:
        raise ConfigError(f"{prefix}{e}") from None


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> Config:
    """Read a TOML file (or use the defaults when ``path`` is None) and validate it.

    ``overrides`` is a nested dict merged over the file (used by CLI flags).
    """
    data: dict[str, Any] = {}
    if path is not None:
        p = Path(path)
        data = read_config_toml(p)
    if overrides:
        data = merge(data, overrides)
    return from_dict(Config, data)


def to_dict(obj: Any) -> Any:
    """Dataclass -> plain TOML-compatible structure (tuples become lists)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple):
        return [to_dict(v) for v in obj]
    return obj


def describe(obj: Any, prefix: str = "") -> list[str]:
    """One line per leaf option: ``key = value  # help``, walking the fields (for start-up logs)."""
    lines: list[str] = []
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            lines.extend(describe(value, key + "."))
        elif isinstance(value, tuple) and value and dataclasses.is_dataclass(value[0]):
            for i, item in enumerate(value):
                lines.extend(describe(item, f"{key}[{i}]."))
        else:
            if f.metadata.get("secret") and value:
                shown = "'***'"
            else:  # credentials inside a URL (rtsp://user:pass@...) never reach a log
                shown = redact_url(repr(to_dict(value)))
            lines.append(f"{key} = {shown}  # {f.metadata.get('help', '')}")
    return lines

"""What an MCAP recording holds (docs/dataset.md, "MCAP recordings"): its topics, the JSON
schema of each of our channels, and the messages of both kinds as bytes.

Foxglove's well-known schemas, protobuf-encoded, where one fits (what Foxglove and
PlotJuggler display without help): ``/camera/image`` foxglove.CompressedImage (the PNG bytes
the replay decodes), ``/pose`` foxglove.PoseInFrame (the pose sent, frame ``world_ned``),
``/tf`` foxglove.FrameTransforms (``world_ned`` -> ``body_frd`` from the sent pose,
``body_frd`` -> ``camera`` from the calibration), ``/log`` foxglove.Log. Our own channels
are JSON with a JSON schema each (``SCHEMAS``): what the replay needs to be exact.

Times: every ``time_us`` is the companion's monotonic clock (the pipeline's); an MCAP log
time is ``time_us * 1000`` [ns] on that clock (not the Unix epoch). Floats are JSON numbers
written as Python's shortest exact text (``json.dumps``): they read back to the same double;
an unknown value (NaN) is ``null``. Frames: NED world, FRD body, OpenCV camera
(docs/architecture.md, "Frames, units, names").
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.timestamp_pb2 import Timestamp

from companion.geometry import so3
from companion.types import F64, AttitudeSample, ImuSample, PoseEstimate, RangeSample

WORLD_FRAME = "world_ned"  # local NED at the origin of the published poses
BODY_FRAME = "body_frd"
CAMERA_FRAME = "camera"  # OpenCV: x right, y down, z along the optical axis

IMAGE = "/camera/image"
POSE = "/pose"
TF = "/tf"
LOG = "/log"
FRAME = "/companion/frame"
RANGE = "/companion/range"
ATTITUDE = "/companion/attitude"
IMU = "/companion/imu"
PUBLISHED = "/companion/published"
STATE = "/companion/state"

PROTOBUF_TOPICS: dict[str, Any] = {
    IMAGE: CompressedImage,
    POSE: PoseInFrame,
    TF: FrameTransforms,
    LOG: Log,
}

_INT = {"type": "integer", "minimum": 0}
_NUM = {"type": "number"}
_OPT_NUM = {"type": ["number", "null"]}


def _vector(n: int, item: dict[str, Any] = _NUM, nullable: bool = False) -> dict[str, Any]:
    array = {"type": "array", "items": item, "minItems": n, "maxItems": n}
    return {"oneOf": [array, {"type": "null"}]} if nullable else array


def _schema(
    title: str, description: str, props: dict[str, Any], optional: Sequence[str] = ()
) -> dict[str, Any]:
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "description": description,
        "type": "object",
        "properties": props,
        "required": [k for k in props if k not in optional],
    }


_FED = {"fed_before_frame": {**_INT, "description": "index of the frame it was fed before"}}
SCHEMAS: dict[str, dict[str, Any]] = {
    FRAME: _schema(
        "companion.Frame",
        "a frame the pipeline took, written after its image and the samples fed before it: "
        "index (0, 1, ...), time_us at exposure, the camera's seq, held (kept from the VO)",
        {"index": _INT, "time_us": _INT, "seq": _INT, "held": {"type": "boolean"}},
    ),
    RANGE: _schema(
        "companion.RangeSample",
        "a distance sensor's reading as fed [m]; signal_quality as DISTANCE_SENSOR's",
        {
            "time_us": _INT,
            "sensor_id": _INT,
            "distance_m": _NUM,
            "min_m": _NUM,
            "max_m": _NUM,
            "signal_quality": _INT,
            "true_distance_m": _OPT_NUM,
            **_FED,
        },
        optional=("true_distance_m",),
    ),
    ATTITUDE: _schema(
        "companion.AttitudeSample",
        "the autopilot's attitude as fed: quat_wxyz R_world_body (NED <- FRD), body rates",
        {"time_us": _INT, "quat_wxyz": _vector(4), "rates_rad_s": _vector(3), **_FED},
    ),
    IMU: _schema(
        "companion.ImuSample",
        "SCALED_IMU as fed: specific force [m/s^2], rates [rad/s], field [gauss], body FRD",
        {
            "time_us": _INT,
            "accel_frd_m_s2": _vector(3),
            "gyro_frd_rad_s": _vector(3, nullable=True),
            "mag_frd_gauss": _vector(3, nullable=True),
            **_FED,
        },
    ),
    PUBLISHED: _schema(
        "companion.PublishedPose",
        "a pose sent to the autopilot: NED position [m], quat_wxyz NED <- FRD, NED velocity "
        "[m/s] (null: unknown), reset_counter as sent, quality [%], covariance diagonal "
        "(x y z [m^2], roll pitch yaw [rad^2]; null: unknown)",
        {
            "time_us": _INT,
            "position_ned_m": _vector(3),
            "quat_wxyz": _vector(4),
            "velocity_ned_m_s": _vector(3, _OPT_NUM),
            "reset_counter": _INT,
            "quality_pct": _INT,
            "covariance_diag": _vector(6, _OPT_NUM, nullable=True),
        },
        optional=("covariance_diag",),
    ),
    STATE: _schema(
        "companion.State",
        "the pipeline after a frame (time_us: the frame's): the VO's state, features, "
        "keyframes and resets; the published scale method, its scale [m per VO unit] and "
        "sigma (null before the first), the sensors of its last update; roll and pitch from "
        "the distance sensors [deg] and their sigma; d-Pose corrections; the autopilot's "
        "clock: autopilot_offset_us = ours - the autopilot's (its boot time, as PX4's .ulg "
        "and ArduPilot's .bin stamp), null until time sync converged",
        {
            "time_us": _INT,
            "vo_state": {"type": "string"},
            "features": _INT,
            "keyframes": _INT,
            "vo_resets": _INT,
            "method": {"type": "string"},
            "scale": _OPT_NUM,
            "scale_sigma": _OPT_NUM,
            "sensors_used": _INT,
            "roll_deg": _OPT_NUM,
            "pitch_deg": _OPT_NUM,
            "tilt_sigma_deg": _OPT_NUM,
            "dpose_used": _INT,
            "autopilot_offset_us": _OPT_NUM,
        },
    ),
}


# ------------------------------------------------------------------------------ JSON
def _floats(values: Any) -> list[float | None]:
    """Floats as JSON numbers (exact), NaN as null."""
    return [None if math.isnan(v) else v for v in map(float, values)]


def to_json(data: dict[str, Any]) -> bytes:
    """A message as compact JSON (no NaN: the caller wrote unknowns as null)."""
    return json.dumps(data, separators=(",", ":"), allow_nan=False).encode()


def range_json(r: RangeSample, fed: int, true_m: float | None = None) -> bytes:
    data: dict[str, Any] = {
        "time_us": r.time_us,
        "sensor_id": r.sensor_id,
        "distance_m": float(r.distance_m),
        "min_m": float(r.min_m),
        "max_m": float(r.max_m),
        "signal_quality": r.signal_quality,
        "fed_before_frame": fed,
    }
    if true_m is not None:
        data["true_distance_m"] = _floats([true_m])[0]
    return to_json(data)


def attitude_json(a: AttitudeSample, fed: int) -> bytes:
    return to_json(
        {
            "time_us": a.time_us,
            "quat_wxyz": _floats(a.quat_wxyz),
            "rates_rad_s": _floats(a.rates_rad_s),
            "fed_before_frame": fed,
        }
    )


def imu_json(m: ImuSample, fed: int) -> bytes:
    gyro, mag = m.gyro_frd_rad_s, m.mag_frd_gauss
    return to_json(
        {
            "time_us": m.time_us,
            "accel_frd_m_s2": _floats(m.accel_frd_m_s2),
            "gyro_frd_rad_s": None if gyro is None else _floats(gyro),
            "mag_frd_gauss": None if mag is None else _floats(mag),
            "fed_before_frame": fed,
        }
    )


def frame_json(index: int, time_us: int, seq: int, held: bool) -> bytes:
    return to_json({"index": index, "time_us": time_us, "seq": seq, "held": held})


def published_json(
    time_us: int,
    position_ned_m: F64,
    quat_wxyz: F64,
    velocity_ned_m_s: F64,
    reset_counter: int,
    quality_pct: int,
    covariance_6x6: F64 | None = None,
) -> bytes:
    data: dict[str, Any] = {
        "time_us": time_us,
        "position_ned_m": _floats(position_ned_m),
        "quat_wxyz": _floats(quat_wxyz),
        "velocity_ned_m_s": _floats(velocity_ned_m_s),
        "reset_counter": reset_counter,
        "quality_pct": quality_pct,
    }
    if covariance_6x6 is not None:
        data["covariance_diag"] = _floats(np.diag(covariance_6x6))
    return to_json(data)


def _opt(value: float | None) -> float | None:
    return None if value is None else _floats([value])[0]


def state_json(time_us: int, status: Any, autopilot_offset_us: float | None) -> bytes:
    """/companion/state of the pipeline's status after a frame (``status``: a
    ``companion.pipeline.PipelineStatus``, read by name)."""
    return to_json(
        {
            "time_us": time_us,
            "vo_state": str(status.vo_state),
            "features": int(status.features),
            "keyframes": int(status.keyframes),
            "vo_resets": int(status.vo_resets),
            "method": str(status.method),
            "scale": _opt(status.scale),
            "scale_sigma": _opt(status.scale_sigma),
            "sensors_used": int(status.sensors_used),
            "roll_deg": _opt(status.roll_deg),
            "pitch_deg": _opt(status.pitch_deg),
            "tilt_sigma_deg": _opt(status.tilt_sigma_deg),
            "dpose_used": int(status.dpose_used),
            "autopilot_offset_us": _opt(autopilot_offset_us),
        }
    )


# ------------------------------------------------------------------------------ protobuf
def descriptor_set(message_class: Any) -> bytes:
    """The FileDescriptorSet of a protobuf message class with every file it depends on (the
    schema data of an MCAP channel of encoding "protobuf")."""
    out = FileDescriptorSet()
    seen: set[str] = set()

    def add(file: Any) -> None:
        for dep in file.dependencies:
            if dep.name not in seen:
                seen.add(dep.name)
                add(dep)
        file.CopyToProto(out.file.add())

    add(message_class.DESCRIPTOR.file)
    return bytes(out.SerializeToString())


def _stamp(time_us: int) -> Timestamp:
    return Timestamp(seconds=time_us // 1_000_000, nanos=(time_us % 1_000_000) * 1000)


def image_message(time_us: int, data: bytes, image_format: str) -> bytes:
    """foxglove.CompressedImage of an encoded frame (``image_format``: "png" or "jpeg")."""
    msg = CompressedImage(
        timestamp=_stamp(time_us), frame_id=CAMERA_FRAME, data=data, format=image_format
    )
    return bytes(msg.SerializeToString())


def _transform(time_us: int, parent: str, child: str, T_parent_child: F64) -> FrameTransform:
    """foxglove.FrameTransform: the child frame's origin and orientation in the parent's."""
    t = FrameTransform(timestamp=_stamp(time_us), parent_frame_id=parent, child_frame_id=child)
    x, y, z = (float(v) for v in T_parent_child[:3, 3])
    t.translation.x, t.translation.y, t.translation.z = x, y, z
    w, qx, qy, qz = (float(v) for v in so3.matrix_to_quat(T_parent_child[:3, :3]))
    t.rotation.w, t.rotation.x, t.rotation.y, t.rotation.z = w, qx, qy, qz
    return t


def pose_messages(pose: PoseEstimate, T_body_cam: F64) -> tuple[bytes, bytes]:
    """foxglove.PoseInFrame (in ``world_ned``) and foxglove.FrameTransforms (world -> body,
    body -> camera) of a pose sent to the autopilot."""
    q = [float(v) for v in pose.quat_wxyz_ned_frd]
    p = [float(v) for v in pose.position_ned_m]
    msg = PoseInFrame(timestamp=_stamp(pose.time_us), frame_id=WORLD_FRAME)
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = p
    o = msg.pose.orientation
    o.w, o.x, o.y, o.z = q
    T_world_body = np.eye(4)
    T_world_body[:3, :3] = so3.quat_to_matrix(q)
    T_world_body[:3, 3] = p
    tf = FrameTransforms(
        transforms=[
            _transform(pose.time_us, WORLD_FRAME, BODY_FRAME, T_world_body),
            _transform(pose.time_us, BODY_FRAME, CAMERA_FRAME, T_body_cam),
        ]
    )
    return bytes(msg.SerializeToString()), bytes(tf.SerializeToString())


LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "FATAL")


def log_message(
    time_us: int, text: str, level: str = "WARNING", name: str = "companion.recorder"
) -> bytes:
    """foxglove.Log of a line: ``level`` one of LOG_LEVELS; ``name`` who said it
    (companion.recorder, companion.service: the service's warnings, companion.statustext:
    the lines sent to the ground station)."""
    msg = Log(timestamp=_stamp(time_us), level=Log.Level.Value(level), message=text, name=name)
    return bytes(msg.SerializeToString())


def image_of(message: bytes) -> tuple[bytes, str]:
    """The encoded image and its format of a foxglove.CompressedImage (DecodeError: bad)."""
    msg = CompressedImage()
    msg.ParseFromString(message)
    return bytes(msg.data), str(msg.format)

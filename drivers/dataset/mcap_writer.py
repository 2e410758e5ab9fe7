"""Write a flight recording as one MCAP file (``McapDatasetWriter``, the flight recorder's
default; docs/dataset.md, "MCAP recordings"): chunked, zstd-compressed, the channels of
``mcap_schemas``, the calibration and the algorithm options as attachments.

Crash safety: the file is appended to, chunk by chunk. A chunk is closed when it holds
``chunk_bytes`` (4 MB: about 16 grey frames at 640 x 480) and at every :meth:`sync` (the
recorder's, once a second), then written to the OS and fsynced; so a process killed at any
point (SIGKILL) or a power cut loses at most the chunk it was filling, and the reader
(``mcap_reader``) recovers every whole chunk of a file that has no footer. Per frame the
samples fed before it come first, then its image, then its frame record: a frame whose record
was lost is not part of the recording, nor are the samples fed before it.

Images: lossless PNG by default, of the grey image when nothing in the pipeline reads colour
(``image = "grey"``: the VO turns every frame grey with OpenCV's fixed-point BGR2GRAY, whose
weights sum to one, so the grey image expanded to three channels turns back into the same
grey, and the replay is exact) or of the BGR image (``"colour"``: d-Pose's red marks).
"""

from __future__ import annotations

import contextlib
import datetime
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from mcap.writer import CompressionType, Writer
from numpy.typing import NDArray

from companion.config import Config, to_dict
from companion.drivers.dataset import mcap_schemas as ms
from companion.drivers.dataset.format import ALGORITHM_SECTIONS, FORMAT_NAME, FORMAT_VERSION
from companion.drivers.dataset.toml_text import toml_dumps
from companion.drivers.dataset.writer import calibration_tables, png_params
from companion.drivers.files import open_new
from companion.errors import DatasetError
from companion.types import AttitudeSample, CameraFrame, ImuSample, PoseEstimate, RangeSample

CHUNK_BYTES = 4 << 20  # a chunk closes at this size (and at every sync): what a kill may lose
MCAP_PROFILE = ""  # no ROS profile: our own JSON channels beside Foxglove's protobuf ones
META_NAME = "companion-dataset"  # the metadata record written at the start
END_NAME = "companion-recording-end"  # the metadata record written when the recorder closes
IMAGE_MODES = ("grey", "colour")
_MEDIA_TOML = "application/toml"


def mcap_path(record_dir: str | Path) -> Path:
    """The file an MCAP recording of ``record.dir`` goes into: the path with ``.mcap`` added
    unless it already ends so (``flights/{start}`` -> ``flights/20261128-234500.mcap``)."""
    p = Path(record_dir)
    return p if p.suffix == ".mcap" else p.with_name(p.name + ".mcap")


def meta_strings(meta: dict[str, Any]) -> dict[str, str]:
    """A metadata record's map (strings only): booleans as true/false, the rest as text."""
    return {k: str(v).lower() if isinstance(v, bool) else str(v) for k, v in meta.items()}


class McapDatasetWriter:
    """One MCAP recording, written frame by frame (the interface of ``DatasetWriter``:
    ``encode``, ``frame_bytes``, ``write_frame``, ``write_pose``, ``sync``, ``close``).
    Created new (O_EXCL | O_NOFOLLOW: FileExistsError when anything is at ``path``). Not
    thread-safe: one thread writes."""

    def __init__(
        self,
        path: Path,
        config: Config,
        *,
        image: str = "grey",
        image_format: str = "png",
        png_compression: int = 1,
        jpg_quality: int = 95,
        software: str = "",
        chunk_bytes: int = CHUNK_BYTES,
        meta: dict[str, Any] | None = None,
    ) -> None:
        if image not in IMAGE_MODES:
            raise DatasetError(f"record.image must be one of {IMAGE_MODES}, got {image!r}")
        if image_format not in ("png", "jpg"):
            raise DatasetError(f"image format must be png or jpg, got {image_format!r}")
        self.path = path
        self.image = image
        self.image_format = image_format
        self._encode_params = (
            png_params(png_compression)
            if image_format == "png"
            else [cv2.IMWRITE_JPEG_QUALITY, jpg_quality]
        )
        self.T_body_cam = config.camera.T_body_cam()
        self.frames = 0
        self.poses = 0
        self.bytes_written = 0
        self.last_time_us = 0  # of the newest message (where the stop reason goes on /log)
        self.meta: dict[str, Any] = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "software": software,
            "source": "recorder",
            "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "clock": "time_us: the recording machine's monotonic clock (the pipeline's); "
            "MCAP log times are time_us * 1000 ns on it",
            "world": "none",
            "ingest_order": True,
            "frames_checked": True,
            "image": image,
            "image_format": image_format,
            **(meta or {}),
        }
        self._file = open_new(path, binary=True)
        try:
            self._mcap = Writer(
                self._file, chunk_size=chunk_bytes, compression=CompressionType.ZSTD
            )
            self._mcap.start(MCAP_PROFILE, f"companion {software}".strip())
            self._mcap.add_metadata(META_NAME, meta_strings(self.meta))
            algo = {k: to_dict(getattr(config, k)) for k in ALGORITHM_SECTIONS}
            for name, table in (
                ("calibration.toml", calibration_tables(config)),
                ("config.toml", algo),
            ):
                blob = toml_dumps(table).encode()
                self._mcap.add_attachment(0, 0, name, _MEDIA_TOML, blob)
                self.bytes_written += len(blob)
            self._channels = self._register()
            self.sync()  # the header, metadata and attachments are on the disk
        except BaseException:  # e.g. a full disk: no half-made recording is left behind
            self._file.close()
            with contextlib.suppress(OSError):
                path.unlink()
            raise

    def _register(self) -> dict[str, int]:
        """The schema and channel of every topic; their ids by topic."""
        ids: dict[str, int] = {}
        for topic, message_class in ms.PROTOBUF_TOPICS.items():
            name = message_class.DESCRIPTOR.full_name
            schema = self._mcap.register_schema(name, "protobuf", ms.descriptor_set(message_class))
            ids[topic] = self._mcap.register_channel(topic, "protobuf", schema)
        for topic, schema_json in ms.SCHEMAS.items():
            data = ms.to_json(schema_json)
            schema = self._mcap.register_schema(schema_json["title"], "jsonschema", data)
            ids[topic] = self._mcap.register_channel(topic, "json", schema)
        return ids

    def _add(self, topic: str, time_us: int, data: bytes) -> None:
        ns = time_us * 1000
        self.last_time_us = max(self.last_time_us, time_us)
        self._mcap.add_message(self._channels[topic], ns, data, ns)
        self.bytes_written += len(data) + 31  # the message record's own fields

    def encode(self, image_bgr: NDArray[np.uint8]) -> bytes:
        """The frame's PNG (or JPEG) bytes, grey or colour as chosen (the costly part; any
        thread may call it)."""
        img = image_bgr
        if self.image == "grey" and img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)  # the VO's own grey, exactly
        ok, buf = cv2.imencode(f".{self.image_format}", img, self._encode_params)
        if not ok:
            raise DatasetError(f"cannot encode a {image_bgr.shape} image as {self.image_format}")
        return bytes(buf)

    def frame_bytes(self, encoded: bytes, n_ranges: int, n_attitudes: int, n_imus: int = 0) -> int:
        """About what a frame adds to the file [bytes] (for a disk budget; the JSON samples
        compress, the image does not)."""
        return len(encoded) + 150 + 200 * n_ranges + 200 * n_attitudes + 250 * n_imus

    def write_frame(
        self,
        frame: CameraFrame,
        encoded: bytes,
        ranges: Sequence[RangeSample],
        attitudes: Sequence[AttitudeSample],
        imus: Sequence[ImuSample] = (),
        held: bool = False,
        true_range_m: Sequence[float] | None = None,
    ) -> None:
        """Append one frame with the samples fed before it (in the order they were fed:
        attitudes, IMU, ranges), then its image, then its frame record. ``encoded``: PNG or
        JPEG bytes (told apart by their signature); ``true_range_m``: a converted dataset's
        true distances (NaN: unknown)."""
        k = self.frames
        for a in attitudes:
            self._add(ms.ATTITUDE, a.time_us, ms.attitude_json(a, k))
        for m in imus:
            self._add(ms.IMU, m.time_us, ms.imu_json(m, k))
        for i, r in enumerate(ranges):
            true_m = None if true_range_m is None else true_range_m[i]
            self._add(ms.RANGE, r.time_us, ms.range_json(r, k, true_m))
        kind = "jpeg" if encoded[:2] == b"\xff\xd8" else "png"
        self._add(ms.IMAGE, frame.time_us, ms.image_message(frame.time_us, encoded, kind))
        self._add(ms.FRAME, frame.time_us, ms.frame_json(k, frame.time_us, frame.seq, held))
        self.frames += 1

    def write_pose(self, pose: PoseEstimate) -> None:
        """Append a pose the service sent: /companion/published (exact, with its reset
        counter and quality), /pose and /tf for the viewers."""
        t = pose.time_us
        self._add(
            ms.PUBLISHED,
            t,
            ms.published_json(
                t,
                pose.position_ned_m,
                pose.quat_wxyz_ned_frd,
                pose.velocity_ned_m_s,
                pose.reset_counter,
                pose.quality_pct,
                pose.covariance_6x6 if np.isfinite(pose.covariance_6x6).any() else None,
            ),
        )
        pose_msg, tf_msg = ms.pose_messages(pose, self.T_body_cam)
        self._add(ms.POSE, t, pose_msg)
        self._add(ms.TF, t, tf_msg)
        self.poses += 1

    def write_published(self, data: bytes, time_us: int) -> None:
        """Append a /companion/published message as given (a conversion's)."""
        self._add(ms.PUBLISHED, time_us, data)
        self.poses += 1

    def log(
        self, time_us: int, text: str, level: str = "WARNING", name: str = "companion.recorder"
    ) -> None:
        """A line on /log (foxglove.Log; ``level`` one of ``mcap_schemas.LOG_LEVELS``)."""
        self._add(ms.LOG, time_us, ms.log_message(time_us, text, level, name))

    def write_state(self, time_us: int, status: Any, autopilot_offset_us: float | None) -> None:
        """The pipeline's state after the frame of ``time_us`` on /companion/state (for the
        viewers: a replay recomputes it)."""
        self._add(ms.STATE, time_us, ms.state_json(time_us, status, autopilot_offset_us))

    def sync(self) -> None:
        """Close the chunk being filled, write it to the OS and fsync the file."""
        self._mcap.flush()  # type: ignore[no-untyped-call]
        os.fsync(self._file.fileno())

    def close(self, stop_reason: str = "") -> None:
        """Say why the recording stopped (on /log, at the newest message's time), write the
        end's metadata (complete, frames, published, stop_reason), the MCAP summary and
        footer, and fsync."""
        if self._file.closed:
            return
        try:
            if stop_reason:
                self.log(self.last_time_us, f"recording stopped: {stop_reason}")
            self._mcap.flush()  # type: ignore[no-untyped-call]  # the last chunk, then the end
            end = {
                "complete": True,
                "frames": self.frames,
                "published": self.poses,
                "stop_reason": stop_reason,
            }
            self.meta.update(end)
            self._mcap.add_metadata(END_NAME, meta_strings(end))
            self._mcap.finish()  # type: ignore[no-untyped-call]
            self._file.flush()
            os.fsync(self._file.fileno())
            self.bytes_written = os.fstat(self._file.fileno()).st_size
        finally:
            self._file.close()

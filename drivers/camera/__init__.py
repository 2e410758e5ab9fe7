"""Camera sources: GStreamer pipelines (``gst:``), Raspberry Pi CSI cameras (``picamera2:``),
V4L2 / UVC devices and other cv2.VideoCapture inputs (video files, network streams), image
folders (our dataset format and EuRoC) and the SITL loopback stream.

Every source is iterated in a worker thread (``read()`` blocks) and yields CameraFrame with
``time_us`` in the companion's monotonic clock at exposure and a (H, W, 3) BGR image:
- GStreamer (drivers/camera/gst.py): the buffer's PTS on the pipeline clock, which we set to a
  CLOCK_MONOTONIC system clock (see that module);
- picamera2 (drivers/camera/picamera2.py): libcamera's SensorTimestamp + half the exposure;
- VideoCapture: with the V4L2 backend the buffer's timestamp (``CAP_PROP_POS_MSEC``; the
  kernel stamps buffers with CLOCK_MONOTONIC, uvcvideo at the start of the frame) when it is
  plausible (not in the future, at most 0.5 s before ``grab()`` returned), else the time
  ``grab()`` returned (FFmpeg: its position is stream time, not our clock);
- folders: the recorded times, shifted so that the first frame is "now" (replayed at the
  recorded rate, or as fast as possible with ``realtime=False``);
- the SITL stream: the time written by the simulator (same machine, same monotonic clock).
``stamps`` says where the last frame's time came from.

``url`` forms (config ``service.camera_url``): ``sitl://HOST:PORT``, ``folder:PATH[?fast]``,
``gst:PIPELINE`` (ending in ``appsink``; a bare pipeline with ``!`` is taken as ``gst:`` too),
``picamera2:[N]`` (camera N, default 0), ``/dev/videoN`` or an integer (V4L2), anything else
goes to VideoCapture (a file, ``rtsp://...``, ``http://...``).

What was asked of the camera (``CaptureRequest``, from the ``[camera]`` table: width, height,
rate_hz, fourcc, exposure_us) is applied where the source can apply it (V4L2 devices, picamera2)
and read back: a device that sets something else is refused with CameraError naming the key. On
every source, a frame whose size is not the calibrated ``camera.width`` x ``camera.height`` is
refused the same way (intrinsics of another size would give a wrong metric pose, silently).

The modules: ``source`` (the contract), ``sitl_stream`` (its wire format too), ``folder``,
``video_capture``, ``gst``, ``picamera2`` and ``urls`` (``open_camera``).
"""

from companion.drivers.camera.folder import MAX_REPLAY_GAP_S, FolderSource
from companion.drivers.camera.sitl_stream import SitlStream, encode_frame
from companion.drivers.camera.source import (
    MAX_DRIVER_STAMP_AGE_US,
    CameraError,
    CameraSource,
    CaptureRequest,
    check_frame_size,
    plausible_stamp_us,
)
from companion.drivers.camera.urls import check_camera_url, is_gst_pipeline, open_camera
from companion.drivers.camera.video_capture import (
    VideoCaptureSource,
    driver_stamp_us,
    fourcc_code,
    fourcc_text,
    is_video_file,
    uvc_readback_problems,
    uvc_settings,
)

__all__ = [
    "MAX_DRIVER_STAMP_AGE_US",
    "MAX_REPLAY_GAP_S",
    "CameraError",
    "CameraSource",
    "CaptureRequest",
    "FolderSource",
    "SitlStream",
    "VideoCaptureSource",
    "check_camera_url",
    "check_frame_size",
    "driver_stamp_us",
    "encode_frame",
    "fourcc_code",
    "fourcc_text",
    "is_gst_pipeline",
    "is_video_file",
    "open_camera",
    "plausible_stamp_us",
    "uvc_readback_problems",
    "uvc_settings",
]

"""The service's report: the status `companion status` shows (and MQTT publishes), and the
exit summary.

Inputs: the parts' state, read on the event loop: ``ServiceStats``, the pipeline's frozen
status snapshot (never the pipeline itself, but for a counter the worker only increments),
the frame intake (under its lock), the autopilot session's clock syncs, the link's, the
recorder's, MQTT's and the status socket's counters. Outputs: ``status()`` and ``summary()``
(JSON-ready dicts: times [s], latencies [ms], rates [Hz], headings [deg]), ``write_report``.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.drivers.files import atomic_write
from companion.redact import redact_text
from companion.service.autopilot_requests import EkfOrigin
from companion.service.autopilot_session import AutopilotSession
from companion.service.frame_intake import FrameIntake
from companion.service.gps_frame import GpsFrame
from companion.service.mqtt import MqttPublisher
from companion.service.operator_messages import OperatorMessages
from companion.service.recorder import Recorder
from companion.service.runtime import AutopilotKind, Runtime
from companion.service.status import StatusServer
from companion.service.worker import PipelineWorker

if TYPE_CHECKING:  # aiohttp is loaded with the page only (app.py)
    from companion.service.web import WebServer


@dataclass
class ReportSources:
    """Where the report reads from (the service's parts and components)."""

    link: Any
    camera: Any
    camera_url_shown: str
    session: AutopilotSession
    origin: EkfOrigin
    intake: FrameIntake
    worker: PipelineWorker
    operator: OperatorMessages
    recorder: Recorder
    mqtt: MqttPublisher | None
    status_server: StatusServer
    web: WebServer | None = None  # the live page ([web]), when enabled
    gps: GpsFrame | None = None  # [gps] align: the GPS frame


class Report:
    """``status()`` and ``summary()`` of one run."""

    def __init__(self, rt: Runtime, src: ReportSources) -> None:
        self.rt = rt
        self.src = src

    def summary(self) -> dict[str, Any]:
        """Figures of the run so far (the exit report)."""
        s, src = self.rt.stats, self.src
        sync, px4 = src.session.sync, src.session.px4_stamps
        now = self.rt.clock()
        lat = np.array(s.latency_ms)
        proc = np.array(s.process_ms)
        times = np.array(s.publish_times_ns) * 1e-9
        rate = float((len(times) - 1) / (times[-1] - times[0])) if len(times) > 1 else 0.0
        ps = src.worker.status
        return {
            "uptime_s": (now - s.started_ns) * 1e-9,
            "frames_in": s.frames_in,
            "frames_dropped": s.frames_dropped,
            "frames_rejected": s.frames_rejected,
            "frames_processed": s.frames_processed,
            "published": s.published,
            "not_published": s.not_published,
            "waited_for_attitude": ps.waited_for_attitude,
            "publish_rate_hz": rate,
            "latency_ms_p50": _percentile(lat, 50),
            "latency_ms_p99": _percentile(lat, 99),
            "process_ms_p50": _percentile(proc, 50),
            "process_ms_p99": _percentile(proc, 99),
            # frames a second this machine let the pipeline turn over (1 / its mean turn):
            # the most it could publish here, whatever the camera's rate
            "pipeline_capacity_hz": (float(1e3 / np.mean(s.cycle_ms)) if len(s.cycle_ms) else None),
            "ranges_in": s.ranges_in,
            "ranges_rejected": s.ranges_rejected,
            "attitudes_in": s.attitudes_in,
            "imus_in": s.imus_in,
            "imu_gravity_frames": src.worker.status.gravity_frames,
            "timesync_replies": s.timesync_replies,
            "timesync_converged": sync.converged,
            # PX4's side, modelled: whether it converts our stamps; poses sent as of sending
            "px4_converts_stamps": px4.converts,
            "px4_timesync_resets": px4.resets,
            # our answers PX4 discards for their round trip (late, forged), as modelled
            "px4_timesync_rtt_discarded": px4.rtt_discarded,
            "stamped_at_send": s.stamped_at_send,
            "rates_acknowledged": sorted(s.rates_acknowledged),
            "rates_refused": sorted(s.rates_refused),
            "autopilot_offset_ms": sync.offset_at(self.rt.clock()) * 1e-6,
            "timesync_rtt_ms": sync.last_rtt_ns * 1e-6,
            "stale": s.stale,
            "pipeline_errors": s.pipeline_errors,
            "warnings": list(s.warnings),
            "vo_resets": ps.vo_resets,
            # our frame's heading [deg]: the autopilot's when the VO started (None: no attitude),
            # or our compass's (vo.heading_source = magnetometer) over the samples below
            "vo_heading_deg": ps.vo_heading_deg,
            "mag_heading_samples": ps.mag_heading_samples,
            "mag_heading_sigma_deg": ps.mag_heading_sigma_deg,
            "vo_gaps": ps.gaps,  # resets forced by > vo.max_gap_ms without frames
            "vo_held_for_attitude": ps.held_for_attitude,
            "vo_heading_restarts": ps.heading_restarts,
            "reset_counter": s.last_reset_counter,
            "scale": ps.scale,
            "link": vars(src.link.stats),
            "recorder": src.recorder.status(),
            "signing": src.link.signing.counters() if src.link.signing else None,
            "statustext": vars(src.operator.limiter.stats),
            "mqtt": dataclasses.asdict(src.mqtt.stats) if src.mqtt else None,
            "status_socket": dataclasses.asdict(src.status_server.stats),
            "web": src.web.status() if src.web else None,
            "frame": src.gps.status() if src.gps else None,
        }

    def status(self) -> dict[str, Any]:
        """What `companion status` shows (served as JSON on the status socket)."""
        now = self.rt.clock()
        s, p, o = self.rt.stats, self.src.worker.status, self.rt.config.service
        mqtt = self.src.mqtt
        pubs = [t for t in s.publish_times_ns if now - t < 5_000_000_000]
        lat = list(s.latency_ms)[-300:]
        return {
            "uptime_s": (now - s.started_ns) * 1e-9,
            "autopilot": self._autopilot_status(now),
            "camera": self._camera_status(now),
            "vo": {
                "state": "STALLED (no frames)" if self.src.intake.silent else p.vo_state,
                "features": p.features,
                "keyframes": p.keyframes,
                "resets": p.vo_resets,
                "heading_deg": p.vo_heading_deg,
                "heading_from_compass": p.mag_heading_samples > 0,
                # frames kept from a VO that was not tracking for want of an attitude, and
                # maps dropped for starting before the attitude stream: north is the autopilot's
                "held_for_attitude": p.held_for_attitude,
                "heading_restarts": p.heading_restarts,
                # the camera's clock (frames re-timed when its stamps jitter) and its lens: the
                # focal length and k1 checked in flight against the autopilot's rotation
                "frames_retimed": p.clock.retimed if p.clock is not None else 0,
                "stamp_jitter_ms": p.clock.jitter_rms_ms if p.clock is not None else None,
                "focal_ratio": p.lens_focal_ratio,
                "focal_pairs": p.lens_focal_samples,
                "k1_delta": p.lens_k1_delta,
                "lens_learned": list(p.lens_learned) if p.lens_learned is not None else None,
                "lens_warning": p.lens_warning,
            },
            "scale": {
                "method": p.method,
                "value": p.scale,
                "sigma": p.scale_sigma,
                "sensors_used": p.sensors_used,
                "match_rate": {str(k): v for k, v in p.match_rates},
                "ranges_in": s.ranges_in,
                "ranges_rejected": s.ranges_rejected + p.ranges_rejected,
                "rejected_by": dict(s.ranges_rejected_by),
                # the filter held at its scale while every measurement fell outside its gate
                "outside_gate_s": p.scale_outside_gate_s,
                "recoveries": p.scale_recoveries,
            },
            "attitude": {
                "roll_deg": p.roll_deg,
                "pitch_deg": p.pitch_deg,
                "sigma_deg": p.tilt_sigma_deg,
                "compensation": self.rt.config.attitude.compensate,
                "reasons": list(p.tilt_reasons),
            },
            "output": {
                "message": o.output,
                "rate_hz": len(pubs) / 5.0,
                "published": s.published,
                "reset_counter": s.last_reset_counter,
                "latency_ms_p50": float(np.percentile(lat, 50)) if lat else None,
            },
            "mqtt": {
                "enabled": mqtt is not None,
                "connected": mqtt.stats.connected if mqtt else False,
                "queued": mqtt.queued if mqtt else 0,
                "dropped": mqtt.stats.dropped if mqtt else 0,
                "published": mqtt.stats.published if mqtt else 0,
                "unasked": mqtt.stats.unasked if mqtt else 0,  # dropped, counted
            },
            # floods refused
            "status_socket": dataclasses.asdict(self.src.status_server.stats),
            "recorder": self.src.recorder.status(),
            # the live page: where, who watches, what it sent and skipped, why it is off
            "web": self.src.web.status() if self.src.web else {"enabled": False},
            # [gps] align: the output's frame, the GPS verdict, the autopilot's actions
            "frame": self.src.gps.status() if self.src.gps else {"enabled": False},
            "warnings": list(s.warnings),
        }

    def _autopilot_status(self, now: int) -> dict[str, Any]:
        """The status's autopilot section: heartbeat, time sync, message counts, signing."""
        s, link = self.rt.stats, self.src.link
        sync, px4, keeper = (
            self.src.session.sync,
            self.src.session.px4_stamps,
            self.src.origin.keeper,
        )
        kind = s.autopilot_kind
        return {
            "url": self.rt.config.service.mavlink_url,
            "heartbeat_age_s": (now - s.autopilot_heartbeat_ns) * 1e-9
            if s.autopilot_heartbeat_ns
            else None,
            "system_id": s.autopilot_system_id or None,
            "type": s.autopilot or None,
            "ekf_origin": {"held": keeper.held, "sent": keeper.sent, "lost": keeper.lost}
            if kind is AutopilotKind.ARDUPILOT
            else None,
            "timesync_converged": sync.converged,
            "timesync_offset_ms": sync.offset_at(now) * 1e-6 if sync.converged else None,
            "timesync_rtt_ms": sync.last_rtt_ns * 1e-6,
            "px4_converts_stamps": px4.converts if kind is AutopilotKind.PX4 else None,
            "px4_timesync_rtt_discarded": px4.rtt_discarded,
            "stamped_at_send": s.stamped_at_send,
            "rates_acknowledged": sorted(s.rates_acknowledged),
            "rates_refused": sorted(s.rates_refused),
            "rx_messages": link.stats.rx_messages,
            "rx_bad": link.stats.rx_bad,
            "handler_errors": link.stats.handler_errors,
            "foreign_messages": s.foreign_messages + link.stats.rx_foreign,
            "other_address": link.stats.rx_other_address,
            # serial: faster than parsed, dropped
            "rx_overflow_bytes": link.stats.rx_overflow_bytes,
            # udpin: every source claiming the autopilot's system id (two: a spoofer, say)
            "claimants": link.claimants_status(now),
            "rivals_seen": link.stats.rivals_seen,
            "attitudes_rejected": s.attitudes_rejected,
            "imus_rejected": s.imus_rejected,
            "signing": link.signing.counters() if link.signing else None,
        }

    def _camera_status(self, now: int) -> dict[str, Any]:
        """The status's camera section (read under the camera thread's lock)."""
        intake, camera = self.src.intake, self.src.camera
        with intake.lock:
            frames = list(intake.frame_times_ns)
            frames_in, dropped = self.rt.stats.frames_in, self.rt.stats.frames_dropped
            rejected = {k: v for k, v in self.src.worker.pipeline.frame_check.counts.items() if v}
        recent = [t for t in frames if now - t < 2_000_000_000]  # a dead camera shows 0 fps
        fps = (len(recent) - 1) / ((recent[-1] - recent[0]) * 1e-9) if len(recent) > 1 else 0.0
        problem = intake.problem.value if intake.problem else None
        if intake.silent:  # and why, when the driver said (a size refused, an error)
            why = camera.last_error
            problem = "no frames" + (f": {redact_text(why, self.rt.secrets)}" if why else "")
        return {
            "url": self.src.camera_url_shown,
            "fps": fps,
            "frames": frames_in,
            "dropped": dropped,
            "stamps": camera.stamps,
            "last_frame_age_s": (now - frames[-1]) * 1e-9 if frames else None,
            "problem": problem,
            "rejected": rejected,
            "gaps": self.src.worker.status.gaps,
        }

    def write_report(self, path: Path) -> None:
        """The exit summary as JSON, written atomically (a full disk leaves no torn file and
        raises OSError for the caller to report)."""
        atomic_write(path, (json.dumps(self.summary(), indent=2) + "\n").encode(), 0o644)


def _percentile(values: Any, q: float) -> float | None:
    """The ``q``-th percentile of ``values`` (None when there are none)."""
    return float(np.percentile(values, q)) if len(values) else None

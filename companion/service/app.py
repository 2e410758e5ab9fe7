"""The companion service: camera + DISTANCE_SENSOR + ATTITUDE in, VISION_POSITION_ESTIMATE /
ODOMETRY out. ``Service`` is the composition root: it builds the components (camera, link,
rangefinders, status socket, MQTT, recorder) and the parts that share one ``Runtime``
(runtime.py: config, clock, counters, stop, warnings), enters them, and runs their loops.

The parts, each a module with its concern:
- autopilot_session: every message in (a dispatch table by kind), HEARTBEAT, TIMESYNC, the
  model of PX4's time sync; autopilot_requests: message rates, ArduPilot's EKF origin;
- gps_frame ([gps] align): GPS fixes in, our poses in the autopilot's GPS frame out, held
  through a GPS loss (companion/frames/handover.py); gps_actions: the autopilot told;
- frame_intake: the camera reader thread, the frame check, the queue, the wait rule;
- worker: frames and samples through the Pipeline on a worker thread;
- publisher: poses shaped for the autopilot and sent;
- operator_messages: the health check's warnings, STATUSTEXT;
- report: the status and the exit summary; mqtt_feed: what goes to the broker;
- web: the live page in a browser (``[web]``), fed by the worker's 1-slot view (web_view).

Structure: ``Service`` is an async context manager that enters its components through one
AsyncExitStack (a failure part-way closes what was already open) and runs one TaskGroup of
named loops. The service does no maths: conversions to and from the wire are in
``drivers.messages``.

Threads, and the one rule for what crosses them:
- the event loop owns everything but the Pipeline: the link (TIMESYNC requests are answered
  inside the receive callback), ServiceStats, MQTT, the status socket;
- the worker thread owns the Pipeline and publishes a frozen snapshot of its status after
  each frame (worker.py): the status, MQTT and the exit summary read only that;
- the worker thread hands the live page, only while somebody watches, a frozen view of
  references into a 1-slot holder (web_view.py); the page renders it on its own thread;
- the camera reader thread shares only under the frame intake's lock, and reports a camera
  fault's start and end with ``call_soon_threadsafe`` (frame_intake.py);
- serial readers (TFmini, a serial autopilot link) hand their samples and bytes to the loop
  with ``call_soon_threadsafe``.
So another thread either holds the intake's lock, goes through ``call_soon_threadsafe``, or
replaces a frozen snapshot; nothing else is shared.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
from collections.abc import Coroutine
from pathlib import Path
from typing import Any

from companion.config import Config
from companion.drivers import ardupilot, messages
from companion.drivers.status import status_path
from companion.drivers.timesync import ClockSync, RequesterModel
from companion.pipeline import Pipeline
from companion.redact import redact_url
from companion.service import preflight
from companion.service.autopilot_requests import GPS_INPUTS, EkfOrigin, MessageRates
from companion.service.autopilot_session import AutopilotSession
from companion.service.frame_intake import FrameIntake
from companion.service.gps_frame import GpsFrame
from companion.service.mqtt import MqttPublisher
from companion.service.mqtt_feed import MqttFeed
from companion.service.operator_messages import OperatorMessages
from companion.service.publisher import Publisher
from companion.service.recorder import Recorder
from companion.service.report import Report, ReportSources
from companion.service.runtime import Runtime, ServiceStats
from companion.service.state import RESET_COUNTER_FILE, ResetCounter, state_dir
from companion.service.status import StatusServer
from companion.service.systemd import SdNotify
from companion.service.web_view import LatestView
from companion.service.worker import PipelineWorker
from companion.types import VoState

LOCAL_POSITION_NED = 32  # MAVLINK_MSG_ID_LOCAL_POSITION_NED: the autopilot's own estimate


class Service:
    """``async with Service(cfg) as s: await s.run(duration_s)``."""

    def __init__(self, config: Config) -> None:
        from companion.drivers.camera import open_camera
        from companion.drivers.mavlink import MavlinkLink
        from companion.drivers.signing import Signing

        self.config = config
        o = config.service
        # everything the config needs from the machine, before anything starts (exit 2)
        self.preflight_warnings = preflight.check(config)
        self.runtime = rt = Runtime(config)
        self.camera_url_shown = redact_url(o.camera_url)
        self.resets = ResetCounter(state_dir(o.state_dir) / RESET_COUNTER_FILE)
        pipeline = Pipeline(config)  # touched by the worker thread only
        self.camera = open_camera(o.camera_url, camera=config.camera)  # size etc. checked
        # the live page draws the autopilot's own estimate beside ours
        web_inputs = frozenset({LOCAL_POSITION_NED}) if config.web.enabled else frozenset()
        gps_inputs = GPS_INPUTS if config.gps.align else frozenset()
        self.link = MavlinkLink(
            o.mavlink_url,
            o.system_id,
            o.component_id,
            self._on_message,
            Signing.from_options(o.signing),  # a bad key file stops here (exit 2)
            o.mavlink_local_port,
            # the rest is skipped unparsed (floods, streams)
            wanted=messages.SERVICE_INPUTS | ardupilot.ARDUPILOT_INPUTS | web_inputs | gps_inputs,
        )
        self.status_server = StatusServer(status_path(o.status_socket), self.status)
        self.mqtt = MqttPublisher(o.mqtt, o.system_id) if o.mqtt.enabled else None
        self.recorder = Recorder(config.record, config)  # its folder is made at start
        self.systemd = SdNotify()
        # the parts
        self.sync = ClockSync()
        self.px4_stamps = RequesterModel(clock=self.sync)  # its round trips by our clock sync
        self.rates = MessageRates(rt, self.link, self.sync, self.px4_stamps)
        self.origin = EkfOrigin(rt, self.link)
        self.gps = GpsFrame(rt, self.link) if config.gps.align else None
        self.session = AutopilotSession(
            rt,
            self.link,
            {r.sensor_id: r for r in config.rangefinders if not r.serial},
            self.sync,
            self.px4_stamps,
            self.rates,
            self.origin,
            self.gps,
        )
        self.tfminis = [self._tfmini(rf) for rf in config.rangefinders if rf.serial]
        self.intake = FrameIntake(rt, self.camera, pipeline.check_frame)
        self.publisher = Publisher(
            rt, self.link, self.session, self.resets, self.recorder, self.gps
        )
        self.web_view = LatestView() if config.web.enabled else None
        self.worker = PipelineWorker(
            rt, pipeline, self.intake, self.session, self.publisher, self.recorder, self.web_view
        )
        self.web = None
        if self.web_view is not None:
            from companion.service.web import WebServer  # aiohttp: loaded with the page only

            self.web = WebServer(
                rt, config.web, self.web_view, pipeline.camera, config.scale, self.status
            )
            self.worker.on_sent = self.web.on_pose
        self.operator = OperatorMessages(
            rt,
            self.link,
            self.camera,
            self.intake,
            self.worker,
            self.tfminis,
            self.camera_url_shown,
            self.gps,
        )
        self.report = Report(
            rt,
            ReportSources(
                self.link,
                self.camera,
                self.camera_url_shown,
                self.session,
                self.origin,
                self.intake,
                self.worker,
                self.operator,
                self.recorder,
                self.mqtt,
                self.status_server,
                self.web,
                self.gps,
            ),
        )
        self.mqtt_feed = MqttFeed(rt, self.mqtt, self.status, self.publisher) if self.mqtt else None
        self.tasks: list[asyncio.Task[None]] = []  # the running loops
        self._stack: contextlib.AsyncExitStack | None = None

    @property
    def stats(self) -> ServiceStats:
        return self.runtime.stats

    @property
    def pipeline(self) -> Pipeline:
        return self.worker.pipeline

    def _on_message(self, msg: Any, rx_ns: int) -> None:
        """The link's callback (the session is made after the link); the autopilot's
        LOCAL_POSITION_NED (asked for with the live page, or [gps] px4_loss_carry) to the
        page, and with [gps] align to the session too."""
        if self.web is not None and msg.get_msgId() == LOCAL_POSITION_NED:
            if msg.get_srcSystem() == self.config.service.system_id:
                self.web.on_local_position(msg)
            if self.gps is None:
                return
        self.session.on_message(msg, rx_ns)

    def _tfmini(self, rf: Any) -> Any:
        """A rangefinder wired to the companion (drivers.rangefinder)."""
        from companion.drivers.rangefinder import TfminiSerial

        device, baud = rf.serial, 115200
        head, _, tail = rf.serial.rpartition(":")
        if head and tail.isdigit():
            device, baud = head, int(tail)
        return TfminiSerial(
            device, rf.sensor_id, rf.min_m, rf.max_m, self.session.range_from_thread, baud
        )

    # ------------------------------------------------------------------ lifecycle
    def _record_warning(self, text: str) -> None:
        """A warning (already redacted) on the recording's /log."""
        self.recorder.log_line(self.runtime.clock() // 1000, text, "WARNING", "companion.service")

    def _loops(self) -> dict[str, Coroutine[Any, Any, None]]:
        """The loops to run, by task name."""
        loops: dict[str, Coroutine[Any, Any, None]] = {
            "heartbeat": self.session.heartbeat_loop(self._tracking),
            "timesync": self.session.timesync_loop(),
            "rates": self.rates.loop(),
            "origin": self.origin.loop(),
            "camera": self.intake.camera_loop(),
            "pipeline": self.worker.loop(),
            "health": self.operator.health_loop(),
        }
        if self.config.service.statustext.enabled:
            loops["statustext"] = self.operator.statustext_loop()
        if self.gps is not None and self.config.gps.handover != "none":
            loops["gps-handover"] = self.gps.actions.loop()
        if self.systemd.watchdog_s:
            loops["watchdog"] = self._watchdog_loop()
        if self.web is not None:
            loops["web"] = self.web.loop()
        if self.mqtt_feed is not None:
            loops["mqtt-status"] = self.mqtt_feed.status_loop()
            loops["mqtt-pose"] = self.mqtt_feed.pose_loop()
        return loops

    def _tracking(self) -> bool:
        return self.worker.vo_state == VoState.TRACKING

    async def __aenter__(self) -> Service:
        """Enter the components in order through one AsyncExitStack: a failure part-way
        (a second instance on the status socket, a port taken) closes what was entered."""
        loop = self.session.loop = asyncio.get_running_loop()
        o = self.config.service
        async with contextlib.AsyncExitStack() as stack:
            # first: a second instance stops here (exit 2)
            await stack.enter_async_context(self.status_server)
            # let the event loop in often while the worker computes; restored on exit
            stack.callback(sys.setswitchinterval, sys.getswitchinterval())
            sys.setswitchinterval(0.0005)
            stack.callback(self.worker.gc.close)  # the collector as it was
            for drv in self.tfminis:
                drv.start()
                stack.callback(drv.close)
            await stack.enter_async_context(self.link)
            if self.mqtt is not None:
                await stack.enter_async_context(self.mqtt)
            if self.web is not None:  # a port in use is said; the service runs on
                await stack.enter_async_context(self.web)
            # the recorder says why it stopped from its thread:
            warn = self.runtime.warn
            stack.enter_context(self.recorder.running(lambda t: loop.call_soon_threadsafe(warn, t)))
            self.runtime.warning_listeners.append(self._record_warning)
            tg = await stack.enter_async_context(asyncio.TaskGroup())
            for name, coro in self._loops().items():
                self.tasks.append(tg.create_task(coro, name=name))
            self._stack = stack.pop_all()
        for text in self.preflight_warnings:
            self.runtime.warn(text)
        from companion import __version__

        self.operator.offer_start(__version__, self.preflight_warnings)
        self.systemd.ready(f"link {o.mavlink_url}, camera {self.camera_url_shown}")
        return self

    async def __aexit__(self, *exc: Any) -> None:
        """Stop every loop; a loop's exception reaches the caller (as an ExceptionGroup)."""
        self.systemd.stopping()
        self.runtime.stop()
        self.camera.close()
        for task in self.tasks:
            task.cancel()
        if self._stack is not None:  # the link is still open: the last words on it
            self.rates.restore()
            if self.config.service.statustext.enabled:
                self.operator.last_words(self.tasks)
            stack, self._stack = self._stack, None
            await stack.__aexit__(*exc)

    async def run(self, duration_s: float | None = None) -> None:
        """Serve until ``stop()`` or for duration_s seconds."""
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self.runtime.stop_event.wait(), duration_s)
        self.runtime.stop()

    def stop(self) -> None:
        self.runtime.stop()

    @property
    def stopped(self) -> bool:
        """Whether the service was stopped (or its finite camera source ended)."""
        return self.runtime.stopping

    async def _watchdog_loop(self) -> None:
        """WATCHDOG=1 every half WatchdogSec, from the event loop: a stuck loop sends none."""
        assert self.systemd.watchdog_s is not None
        while not self.runtime.stopping:
            self.systemd.watchdog()
            await self.runtime.sleep(self.systemd.watchdog_s / 2)

    # ------------------------------------------------------------------ reporting
    def summary(self) -> dict[str, Any]:
        """Figures of the run so far (the exit report)."""
        return self.report.summary()

    def status(self) -> dict[str, Any]:
        """What `companion status` shows (served as JSON on the status socket)."""
        return self.report.status()

    def write_report(self, path: Path) -> None:
        """The exit summary as JSON, written atomically."""
        self.report.write_report(path)

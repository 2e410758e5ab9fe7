"""Real peers the tests start on 127.0.0.1: free ports and a Mosquitto broker."""

from __future__ import annotations

import asyncio
import fcntl
import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path
from typing import Any

MOSQUITTO = shutil.which("mosquitto") or "/usr/sbin/mosquitto"


# The machine to itself for real time, across the workers of a test run (`make test`: two
# pytest-xdist workers) and across test runs on one machine (two clones' `make test` at once).
# A SITL flight is judged against the wall clock
# (rates, time sync, VO tracking through frames that arrive on time), and so is a real
# autopilot's closed loop, whose bridge also renders the camera live at 30 Hz (about a core).
# Beside another flight or a CPU-bound test they failed (seen: PX4's hover below 99 % fusion
# and over its p95 bound after VO re-initialisations from late frames, ArduPilot's EKF
# failsafe, the faults' and the flood's output rates, the recorder's replay). So every test
# holds the machine shared while it runs, and a flight holds it alone: a SITL flight from the
# end of its prerendering (which runs beside the other worker's tests) to the end of its
# flight (its report, plot and checks run beside them again: realtime_done), a real
# autopilot's closed loop for its whole test. tests/conftest.py names the lock
# (MACHINE_LOCK_ENV: one file per machine, in the system's temp folder; unset: no lock), takes
# it before each test and releases it after. A turnstile (a second lock) lets a waiting flight
# in before the other worker's next test.
# The real autopilots listen on fixed instance numbers and ports (tests/conftest.py), which a
# second run on the machine would take too: a run's autopilot tests hold AUTOPILOTS_LOCK_ENV
# (another file per machine) from the first of them to the end of the last, taken before the
# machine lock (a run waiting for it holds nothing the other run needs).
MACHINE_LOCK_ENV = "COMPANION_TEST_MACHINE_LOCK"
AUTOPILOTS_LOCK_ENV = "COMPANION_TEST_AUTOPILOTS_LOCK"
_machine: list[int] = []  # this process's descriptor of the lock while it holds it
_autopilots: list[int] = []  # the same for the autopilots' lock
# seconds this process waited for the locks since the last waited_s() call: the suite's
# idle time (tests/conftest.py writes it per test to COMPANION_TEST_WAIT_LOG when set)
_waited_s: list[float] = [0.0]


def waited_s() -> float:
    """The seconds waited for the machine or the autopilots since the last call (then 0)."""
    out, _waited_s[0] = _waited_s[0], 0.0
    return out


def _try_lock(path: str, mode: int = fcntl.LOCK_EX) -> int | None:
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, mode | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def _unlock(fd: int) -> None:
    fcntl.flock(fd, fcntl.LOCK_UN)
    os.close(fd)


def _not_counted(since: float) -> float:
    """Give the running test back the time it waited for a lock since ``since`` (monotonic):
    pytest-timeout's alarm (its signal method, ITIMER_REAL) moves on by as much, so that a
    test's limit counts its own work, not the other tests' (of this run or another run).
    Returns now (monotonic): a wait calls it after every poll, so that the alarm never goes
    off while it waits (2026-11-27: with two runs on the machine, three autopilot tests
    timed out in their wait for the other run's autopilots, 60-300 s)."""
    now = time.monotonic()
    _waited_s[0] += now - since
    remaining_s, interval_s = signal.getitimer(signal.ITIMER_REAL)
    if remaining_s > 0:
        signal.setitimer(signal.ITIMER_REAL, remaining_s + now - since, interval_s)
    return now


async def hold_machine_async(exclusive: bool, poll_s: float = 0.1) -> None:
    """Hold the machine, shared or alone, until release_machine(); a process that holds it
    shared and asks for it alone lets go first (two upgrades would wait on each other). Polls,
    moving the test's timeout on by each poll's wait (_not_counted): the wait is not counted,
    however long another run keeps the machine (a lock dies with its holder; a run that hangs
    holding it ends at its own timeouts)."""
    base = os.environ.get(MACHINE_LOCK_ENV)
    if not base:
        return
    release_machine()
    since = time.monotonic()
    while (turn := _try_lock(base + ".turn")) is None:
        await asyncio.sleep(poll_s)
        since = _not_counted(since)
    try:
        mode = fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH
        while (fd := _try_lock(base, mode)) is None:
            await asyncio.sleep(poll_s)
            since = _not_counted(since)
        _machine.append(fd)
    finally:
        _unlock(turn)
        _not_counted(since)


def hold_machine(exclusive: bool) -> None:
    """hold_machine_async() from synchronous code (before a test: tests/conftest.py)."""
    asyncio.run(hold_machine_async(exclusive))


async def realtime_gate() -> None:
    """The SITL autopilot's flight gate (AutopilotOptions.flight_gate): the machine alone."""
    await hold_machine_async(exclusive=True)


async def realtime_done() -> None:
    """The SITL autopilot's end of flight (AutopilotOptions.flight_done): the machine shared
    again, so that the other worker's tests run beside what the test does after its flight (the
    autopilot's report and plot, the service's stop, a replay of its recording, its checks)."""
    await hold_machine_async(exclusive=False)


def release_machine() -> None:
    """Let the other worker run (after each test, tests/conftest.py)."""
    while _machine:
        _unlock(_machine.pop())


def hold_autopilots(poll_s: float = 0.5) -> None:
    """Hold the real autopilots' instance numbers and ports until release_autopilots() (kept
    across the tests of the run's autopilots; waits while another run on the machine has them)."""
    path = os.environ.get(AUTOPILOTS_LOCK_ENV)
    if not path or _autopilots:
        return
    since = time.monotonic()
    while (fd := _try_lock(path)) is None:
        time.sleep(poll_s)
        since = _not_counted(since)
    _autopilots.append(fd)
    _not_counted(since)


def release_autopilots() -> None:
    """After the run's last autopilot test (its module fixtures' processes stopped)."""
    while _autopilots:
        _unlock(_autopilots.pop())


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port nobody listens on right now (TCP by default, or SOCK_DGRAM)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Broker:
    """A Mosquitto process on 127.0.0.1:port (start/stop at will; same port)."""

    def __init__(self, tmp: Path) -> None:
        self.port = free_port()
        self.conf = tmp / "mosquitto.conf"
        self.conf.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\n")
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [MOSQUITTO, "-c", str(self.conf)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", self.port)) == 0:
                    return
            time.sleep(0.05)
        raise RuntimeError("mosquitto did not start")

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(5)
            self.proc = None


# The 320x240 camera the real-autopilot loops fly (config/px4_sitl.toml: the SITL default's
# field of view at half the resolution) with its pixel-sized options: for the flights whose
# assertions are about the service (faults, floods, recordings, messages), not the image.
# A quarter of the pixels to render before the flight (about 6 ms a frame instead of 23 on
# two cores here) and to track during it.
SMALL_CAMERA_CONFIG = "config/px4_sitl.toml"


def small_camera() -> dict:
    """SMALL_CAMERA_CONFIG's [camera] table but its rate, and the pixel-sized keys of its
    [vo] and [scale] tables (``*_px``), as config overrides: the image's size, not that
    file's tuning for PX4 (its gravity prior, its frame rate), so the flights keep their own
    scenario's settings."""
    import tomllib

    with open(SMALL_CAMERA_CONFIG, "rb") as fh:
        data = tomllib.load(fh)
    # the image, not the rate: the loops' 20 Hz is for a real autopilot beside us on 2 cores
    out: dict = {"camera": {k: v for k, v in data["camera"].items() if k != "rate_hz"}}
    for table in ("vo", "scale"):
        out[table] = {k: v for k, v in data[table].items() if k.endswith("_px")}
    return out


def small_camera_takeoff(seed: int, **vo: object) -> object:
    """The config of a vertical take-off from flat ground to ~4.3 m and back (SITL, 14 s: 3.5 s
    on the ground, the climb by 7 s, then down) with :func:`small_camera`'s image and a 2 deg
    gravity prior; ``vo``: more [vo] keys."""
    from companion.config import load_config

    overrides = small_camera()
    overrides["vo"].update(gravity_sigma_deg=2.0, **vo)
    overrides["sitl"] = {
        "terrain": "flat",
        "trajectory": "hover",
        "takeoff_landing": True,
        "seconds": 14.0,
        "seed": seed,
    }
    return load_config(None, overrides)


def sitl_flight(
    tmp_path: Path,
    seconds: float,
    service: dict | None = None,
    config: str = "config/sitl.toml",
    small: bool = False,
    overrides: dict | None = None,
    **autopilot: object,
) -> tuple[object, object]:
    """A config (config/sitl.toml, ``seconds`` of flight) and SITL autopilot options that put
    the autopilot, the service and the camera on free loopback ports, with a prerendered
    camera (the two cores are then the service's and the autopilot's, not the renderer's)
    and the status socket in ``tmp_path``. ``service``: more [service] keys;
    ``config``: the scenario's config file; ``small``: the 320x240 camera (small_camera());
    ``overrides``: more config tables; ``autopilot``: more AutopilotOptions fields (a
    ``time_scale`` < 1 flies in slow motion: slow_motion_overrides() for the durations)."""
    from companion.config import load_config
    from companion.sitl.stub.options import AutopilotOptions
    from companion.toml_files import merge

    udp_stub, udp_us, tcp_cam = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM), 0
    tcp_cam = free_port()
    opts = AutopilotOptions(
        listen_port=udp_stub,
        companion_port=udp_us,
        camera_port=tcp_cam,
        gcs_listen_port=0,
        # the flight starts this long after the gate (1.5 s was tried on 2026-11-29: the
        # status-flood test's 29 Hz floor then failed 3 of 5 runs under load, against 1 of 3
        # with 4 s; not proven harmless, so kept)
        warmup_s=4.0,
        # and ends this long after its last frame: a pose is sent within service.stale_frame_ms
        # (100 ms) of its frame or never, and the autopilot's defaults' 2 s were idle seconds
        # with the machine held alone
        linger_s=0.5,
        prerender=True,
        flight_gate=realtime_gate,  # prerendered beside other tests, then flown alone,
        flight_done=realtime_done,  # then the rest of the test beside other tests again
        **autopilot,  # type: ignore[arg-type]
    )
    svc = {
        "mavlink_url": f"udpin:127.0.0.1:{udp_us}",
        "camera_url": f"sitl://127.0.0.1:{tcp_cam}",
        "status_socket": str(tmp_path / "status.sock"),
        "state_dir": str(tmp_path / "state"),
        **(service or {}),
    }
    flight = merge(overrides or {}, {"sitl": {"seconds": seconds}, "service": svc})
    cfg = load_config(config, merge(small_camera(), flight) if small else flight)
    return cfg, opts


def slow_motion_overrides(config: str, time_scale: float) -> dict:
    """The service's options that are durations of flight (d-Pose's arming after and over a
    hover, its drift per second), as the same stretch of flight lasts at ``time_scale``
    (sitl/stub/autopilot.py: the service lives on the wall clock, the scenario in flight time)."""
    from companion.config import load_config

    d = load_config(config).dpose
    return {
        "dpose": {
            "arm_after_s": d.arm_after_s / time_scale,
            "arm_window_s": d.arm_window_s / time_scale,
            "vo_drift_m_per_s": d.vo_drift_m_per_s * time_scale,
        }
    }


def service_config(
    tmp_path: Path, tables: dict[str, object] | None = None, **service: object
) -> object:
    """The built-in config with a service that has no peers unless told: the autopilot link on
    a free loopback UDP port, a camera URL where nothing listens (the camera loop keeps
    retrying), the status socket in ``tmp_path``; ``service``: [service] keys to override;
    ``tables``: other tables of the config (``{"rangefinders": [...]}``)."""
    from companion.config import load_config

    svc = {
        "mavlink_url": f"udpin:127.0.0.1:{free_port(socket.SOCK_DGRAM)}",
        "camera_url": f"sitl://127.0.0.1:{free_port()}",
        "status_socket": str(tmp_path / "status.sock"),
        "state_dir": str(tmp_path / "state"),
        **service,
    }
    return load_config(None, {**(tables or {}), "service": svc})


def feed_biased_step(pipeline: Any, step: Any, imus: list, k_imu: int, R_err: Any) -> int:
    """Feed a pipeline the IMU samples ``imus[k_imu:]`` up to a SITL step's frame, then the
    step with its autopilot attitudes turned by ``R_err`` (3, 3) (an autopilot's attitude
    error: R_err @ R_world_body); returns the index of the next IMU sample."""
    from companion.geometry import so3
    from companion.offline import feed_step
    from companion.types import AttitudeSample

    while k_imu < len(imus) and imus[k_imu].time_us <= step.frame.time_us:
        pipeline.feed_imu(imus[k_imu])
        k_imu += 1
    biased = [
        AttitudeSample(
            a.time_us, so3.matrix_to_quat(R_err @ so3.quat_to_matrix(a.quat_wxyz)), a.rates_rad_s
        )
        for a in step.attitudes
    ]
    feed_step(
        pipeline, type(step)(step.frame, step.rendered, step.T_world_body, step.ranges, biased)
    )
    return k_imu

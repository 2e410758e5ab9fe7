"""The real ArduCopter in software-in-the-loop (``../shared/ardupilot-sitl/ardupilot-sitl``).

The launcher (README beside it) starts ArduCopter with its own multicopter physics, parameters
wiped to ``copter.parm`` plus a profile (``gps`` | ``vpe`` | ``odom``). Here it is started with
one more defaults file of our own (parameters that apply only at boot: VISO_TYPE, GPS1_TYPE,
RNGFND1_TYPE, ...) and an instance number (``-I N``: every TCP port moves up by 10 N):
SERIAL0 = 5760 + 10 N (the autopilot waits for a client there before it runs), SERIAL1 =
5762 + 10 N, SERIAL2 = 5763 + 10 N.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from pathlib import Path

from companion.errors import SitlError

REPO = Path(__file__).resolve().parents[2]
SHARED_ARDUPILOT = REPO.parent / "shared" / "ardupilot-sitl" / "ardupilot-sitl"
BUILD_HELP = (
    "ArduPilot SITL not found: pass --ardupilot PATH or set ARDUPILOT_SITL to a launcher with "
    "the interface `ardupilot-sitl PROFILE WORKDIR -- ARGS` (../shared/ardupilot-sitl/"
    "ardupilot-sitl is used when present). To build ArduCopter SITL yourself: clone "
    "ArduPilot with its submodules, `./waf configure --board sitl && ./waf copter`, and see "
    "docs/install.md, 'ArduPilot SITL'."
)
PROFILES = ("gps", "vpe", "odom")
SERIAL0_PORT, SERIAL1_PORT, SERIAL2_PORT = 5760, 5762, 5763


def find_ardupilot(path: str | None = None) -> Path:
    """--ardupilot, else $ARDUPILOT_SITL, else ../shared/ardupilot-sitl/ardupilot-sitl;
    SitlError saying how to get one."""
    for cand in (path, os.environ.get("ARDUPILOT_SITL")):
        if cand:
            p = Path(cand).expanduser()
            if p.is_file() and os.access(p, os.X_OK):
                return p.resolve()
            raise SitlError(
                f"ArduPilot SITL launcher {cand!r} is not an executable file. {BUILD_HELP}"
            )
    if SHARED_ARDUPILOT.is_file():
        return SHARED_ARDUPILOT
    raise SitlError(BUILD_HELP)


def available() -> bool:
    """Whether an ArduPilot SITL launcher is found (for tests that skip without one)."""
    try:
        find_ardupilot()
    except SitlError:
        return False
    return True


def runtime_dir(launcher: Path) -> Path | None:
    """The unpacked runtime of the shared launcher (copter.parm, extnav_*.parm), found as the
    launcher finds it (its cache folder keyed by the tarball's cksum); None before the first
    start or for a launcher of another kind."""
    tarball = launcher.parent / "ardupilot-sitl-runtime.tar.gz"
    if not tarball.is_file():
        return None
    with tarball.open("rb") as fh:
        key = subprocess.run(["cksum"], stdin=fh, capture_output=True, check=True).stdout.split()[0]
    if os.environ.get("ARDUPILOT_SITL_CACHE"):
        cache = Path(os.environ["ARDUPILOT_SITL_CACHE"])
    elif os.environ.get("XDG_CACHE_HOME"):
        cache = Path(os.environ["XDG_CACHE_HOME"]) / "ardupilot-sitl"
    else:
        cache = Path.home() / ".cache" / "ardupilot-sitl"
    for base in (
        cache,
        Path(os.environ.get("TMPDIR", "/tmp")) / f"ardupilot-sitl-cache-{os.getuid()}",
    ):
        rt = base / key.decode() / "ardupilot-sitl-runtime"
        if (rt / "copter.parm").is_file():
            return rt
    return None


def port(serial: int, instance: int) -> int:
    """The TCP port of SERIALn (0, 1 or 2) of an instance."""
    return {0: SERIAL0_PORT, 1: SERIAL1_PORT, 2: SERIAL2_PORT}[serial] + 10 * instance


class ArduPilotSitl:
    """``with ArduPilotSitl(work, profile, params, instance) as ap:`` a running ArduCopter (its
    own process group; SIGTERM, then SIGKILL, on exit). ``params`` go into a defaults file of
    their own, on top of the profile's (so those applied only at boot take effect)."""

    def __init__(
        self,
        work: Path,
        profile: str = "odom",
        params: dict[str, float] | None = None,
        instance: int = 0,
        launcher: str | None = None,
    ) -> None:
        if profile not in PROFILES:
            raise SitlError(f"ArduPilot SITL profile {profile!r}: one of {', '.join(PROFILES)}")
        self.launcher = find_ardupilot(launcher)
        self.work = work
        self.profile = profile
        self.params = dict(params or {})
        self.instance = instance
        self.proc: subprocess.Popen[bytes] | None = None
        self.console = work / "ardupilot-console.log"

    def _defaults(self) -> str | None:
        """--defaults with our file on top of the profile's, None before the runtime is unpacked
        (then the params are applied on a second start, see :meth:`start`)."""
        rt = runtime_dir(self.launcher)
        if rt is None:
            return None
        ours = self.work / "companion.parm"
        ours.write_text("".join(f"{k} {v:.10g}\n" for k, v in self.params.items()))
        files = [rt / "copter.parm"]
        if self.profile != "gps":
            files.append(rt / f"extnav_{self.profile}.parm")
        return ",".join(str(f) for f in [*files, ours])

    def start(self) -> None:
        self.work.mkdir(parents=True, exist_ok=True)
        defaults = self._defaults()
        if defaults is None and self.params:  # unpack the runtime once, then start for real
            subprocess.run(
                [str(self.launcher), "nosuchprofile"], capture_output=True, timeout=120, check=False
            )
            defaults = self._defaults()
            if defaults is None:
                raise SitlError(f"cannot find the unpacked runtime of {self.launcher}")
        extra = ["--", "-I", str(self.instance)]
        if defaults is not None:
            extra += ["--defaults", defaults]
        fh = self.console.open("wb")
        self.proc = subprocess.Popen(
            [str(self.launcher), self.profile, str(self.work / "ap"), *extra],
            stdout=fh,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        fh.close()
        self.wait_console(f"bind port {port(0, self.instance)}", 60.0)

    def wait_console(self, text: str, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if text in self.console.read_text(errors="replace"):
                return
            if self.proc is not None and self.proc.poll() is not None:
                raise SitlError(
                    f"ArduPilot SITL exited with {self.proc.returncode}: see {self.console}"
                )
            time.sleep(0.05)
        raise SitlError(
            f"ArduPilot SITL did not print {text!r} within {timeout_s:g} s: see {self.console}"
        )

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self) -> None:
        p, self.proc = self.proc, None
        if p is None or p.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGTERM)
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(5)

    def __enter__(self) -> ArduPilotSitl:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

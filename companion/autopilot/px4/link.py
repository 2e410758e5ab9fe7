"""The MAVSDK session of ``companion px4``: parameters (param plugin), armed state and local
position (telemetry plugin), raw ESTIMATOR_STATUS / GPS_RAW_INT / STATUSTEXT (mavlink_direct),
and PX4's MAVLink shell (shell plugin).

MAVSDK 4 is the ctypes binding of the C++ core (no mavsdk_server); it joins as a ground station
(system 245), so it needs a link of its own to the autopilot: a second MAVLink instance (PX4
SITL's ground-station port, a telemetry radio, USB), or the companion's link while the service
is stopped. MAVSDK talks to PX4 with byte-wise parameter encoding: INT32 values travel as their
own bits, so ``set_param_int`` writes an INT32 correctly, where a float write would not.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections.abc import AsyncGenerator
from typing import Any, TypeVar

from companion.autopilot.params import Param, Target
from companion.autopilot.reach import mavsdk_url
from companion.drivers.px4_shell_text import clean
from companion.errors import AutopilotError, AutopilotUnreachableError

log = logging.getLogger("companion.px4")
T = TypeVar("T")
SHELL_PROMPTS = ("nsh> ", "pxh> ")  # NuttX on a flight controller; PX4 SITL (POSIX) says pxh


def _mavsdk_log(level: Any, message: str, file: str | None, line: int) -> bool:
    log.debug("mavsdk %s: %s", getattr(level, "name", level), message)
    return True  # not on the console: our output is the table


async def _first(stream: AsyncGenerator[T, None], timeout_s: float) -> T | None:
    """The first item of a MAVSDK subscription within timeout_s (None if none)."""
    async with contextlib.aclosing(stream):
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout_s):
                async for item in stream:
                    return item
    return None


class Px4Link:
    """``async with Px4Link(url, timeout_s) as px4:`` a connected PX4 autopilot."""

    def __init__(self, url: str, timeout_s: float = 10.0) -> None:
        self.url = mavsdk_url(url)
        self.timeout_s = timeout_s
        self._mavsdk: Any = None
        self.system: Any = None
        self.system_id = 0
        self.autopilot = ""

    async def __aenter__(self) -> Px4Link:
        from mavsdk import log_subscribe
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk

        log_subscribe(_mavsdk_log)
        conf = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
        self._mavsdk = Mavsdk(conf)
        try:
            await self._mavsdk.add_any_connection(self.url)
        except Exception as e:
            await self.__aexit__()
            raise AutopilotUnreachableError(
                f"cannot open {self.url}: {e} (is the port in use?)"
            ) from None
        self.system = await self._mavsdk.first_autopilot(timeout_s=self.timeout_s)
        if self.system is None:
            await self.__aexit__()
            raise AutopilotUnreachableError(
                f"no autopilot heartbeat on {self.url} within {self.timeout_s:g} s "
                "(wrong port or baud rate, or the autopilot is off)"
            )
        self.system_id = int(await self.system.get_system_id())
        self.autopilot = str(getattr(await self.system.autopilot_type(), "name", "?"))
        if self.autopilot not in ("PX4", "UNKNOWN"):
            await self.__aexit__()
            raise AutopilotError(
                f"{self.url}: the autopilot is {self.autopilot}; this knows PX4 only"
            )
        return self

    async def __aexit__(self, *exc: object) -> None:
        from mavsdk import log_unsubscribe

        if self._mavsdk is not None:
            self._mavsdk.destroy()
            self._mavsdk = None
        log_unsubscribe()

    # ---------------------------------------------------------------- parameters
    async def params(self) -> dict[str, Param]:
        """Every parameter with the type PX4 declares (PARAM_REQUEST_LIST)."""
        from mavsdk.asyncio.plugins.param import ParamAsync

        plugin = ParamAsync(self.system)
        last: Exception | None = None
        for _ in range(3):
            try:
                allp = await plugin.get_all_params()
            except Exception as e:  # a lost PARAM_VALUE on a radio link: ask again
                last = e
                continue
            out = {p.name: Param(p.name, int(p.value), True) for p in allp.int_params}
            out.update({p.name: Param(p.name, float(p.value), False) for p in allp.float_params})
            if out:
                return out
        raise AutopilotError(f"cannot read the parameter list: {last or 'empty'}")

    async def read(self, name: str, is_int: bool) -> int | float:
        """One parameter, read again from the autopilot (PARAM_REQUEST_READ)."""
        from mavsdk.asyncio.plugins.param import ParamAsync

        plugin = ParamAsync(self.system)
        try:
            if is_int:
                return int(await plugin.get_param_int(name))
            return float(await plugin.get_param_float(name))
        except Exception as e:
            raise AutopilotError(f"cannot read {name}: {e}") from None

    async def write(self, target: Target) -> None:
        """PARAM_SET with the parameter's own type (INT32 as INT32, byte-wise)."""
        from mavsdk.asyncio.plugins.param import ParamAsync

        plugin = ParamAsync(self.system)
        try:
            if target.is_int:
                await plugin.set_param_int(target.name, int(target.value))
            else:
                await plugin.set_param_float(target.name, float(target.value))
        except Exception as e:
            raise AutopilotError(f"cannot write {target.name} = {target.value}: {e}") from None

    # ---------------------------------------------------------------- telemetry
    async def armed(self) -> bool:
        """Armed, from the autopilot's HEARTBEAT."""
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        telemetry = TelemetryAsync(self.system)
        value = await _first(telemetry.subscribe_armed(), min(3.0, self.timeout_s))
        return bool(value if value is not None else await telemetry.armed())

    async def watch(self, seconds: float) -> dict[str, Any]:
        """Listen ``seconds``: the last ESTIMATOR_STATUS flags, LOCAL_POSITION_NED count with
        the times of the first and last one and the longest gap between two [s after the
        start], a GPS receiver seen, STATUSTEXTs."""
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        telemetry = TelemetryAsync(self.system)
        direct = MavlinkDirectAsync(self.system)
        start = time.monotonic()
        seen: dict[str, Any] = {
            "estimator_flags": None,
            "local_positions": 0,
            "lpos_first_s": None,
            "lpos_last_s": None,
            "lpos_max_gap_s": None,
            "gps_seen": False,
            "statustexts": [],
        }

        async def estimator() -> None:
            async for m in direct.subscribe_message("ESTIMATOR_STATUS"):
                seen["estimator_flags"] = int(json.loads(m.fields_json)["flags"])

        async def gps() -> None:
            async for m in direct.subscribe_message("GPS_RAW_INT"):
                if int(json.loads(m.fields_json).get("fix_type", 0)) >= 1:
                    seen["gps_seen"] = True

        async def texts() -> None:
            async for m in direct.subscribe_message("STATUSTEXT"):
                if int(m.component_id) != 1:  # the service's own (forwarded), not PX4's
                    continue
                seen["statustexts"].append(str(json.loads(m.fields_json).get("text", "")))

        async def lpos() -> None:
            async for _ in telemetry.subscribe_position_velocity_ned():
                t = time.monotonic() - start
                last = seen["lpos_last_s"]
                if last is None:
                    seen["lpos_first_s"] = t
                else:
                    seen["lpos_max_gap_s"] = max(seen["lpos_max_gap_s"] or 0.0, t - last)
                seen["lpos_last_s"] = t
                seen["local_positions"] += 1

        tasks = [asyncio.create_task(c()) for c in (estimator, gps, texts, lpos)]
        try:
            await asyncio.sleep(seconds)
        finally:
            for t in tasks:
                t.cancel()
            for t in tasks:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await t
        return seen

    # ---------------------------------------------------------------- shell
    async def shell(self, commands: list[str], timeout_s: float = 3.0) -> list[str] | None:
        """The output of each command in PX4's MAVLink shell; None when the shell does not
        answer (no shell on this link or firmware)."""
        from mavsdk.asyncio.plugins.shell import ShellAsync
        from mavsdk.plugins.shell import Device

        shell = ShellAsync(self.system)
        received: asyncio.Queue[str] = asyncio.Queue()

        async def reader() -> None:
            async for r in shell.subscribe_receive():
                received.put_nowait(str(r.data))

        task = asyncio.create_task(reader())
        outputs: list[str] = []
        try:
            await asyncio.sleep(0.1)  # the subscription must exist before the first command
            for command in commands:
                while not received.empty():
                    received.get_nowait()
                try:
                    await shell.send(command, Device.SHELL)
                except Exception as e:
                    log.debug("shell send failed: %s", e)
                    return None
                text = ""
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(timeout_s):
                        while not _complete(text, command):
                            text += await received.get()
                if not text:
                    return None
                outputs.append(clean(text))
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        return outputs


def _complete(text: str, command: str) -> bool:
    """The command's output is in: a prompt after its echo (or after some output). Without
    it each command waits out its timeout (3 s: PX4 SITL's ``pxh>`` took 21 s per check)."""
    t = clean(text)
    start = t.find(command)
    rest = t[start + len(command) :] if start >= 0 else t
    tail = rest.rstrip()
    return any(p in rest and tail.endswith(p.strip()) for p in SHELL_PROMPTS)

"""``companion autopilot configure`` on ArduPilot: write what check asks for with the
parameter's own type (ArduPilot carries every value as a float: an integer as the float of its
value), read every one back, say which need a reboot; through the shared flow
(:mod:`companion.autopilot.configure`), with the blocking pymavlink session run in a thread.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable

from companion.autopilot.ardupilot.check import context, evaluate_rows, header
from companion.autopilot.ardupilot.link import ArduPilotLink
from companion.autopilot.configure import (
    GPS_WATCH_S,
    ConfigureReport,
    ask,
    plan_and_write,
    refuse_if_armed,
)
from companion.autopilot.options import CheckOptions
from companion.autopilot.params import Param, Row, Target, finite_params
from companion.autopilot.reach import resolve_link
from companion.autopilot.report import service_status
from companion.config import Config


class ThreadedParamLink:
    """The blocking :class:`ArduPilotLink` as the flow's :class:`ParamLink` (one call at a
    time, each in a thread)."""

    def __init__(self, link: ArduPilotLink) -> None:
        self.link = link

    async def armed(self) -> bool:
        """Armed, from the autopilot's HEARTBEAT."""
        return await asyncio.to_thread(self.link.armed)

    async def params(self) -> dict[str, Param]:
        """Every parameter."""
        return await asyncio.to_thread(self.link.params)

    async def write(self, target: Target) -> None:
        """PARAM_SET with the parameter's own type."""
        await asyncio.to_thread(self.link.write, target)

    async def read(self, name: str, is_int: bool) -> int | float:
        """One parameter read again (an integer's float rounded back to the integer)."""
        value = await asyncio.to_thread(self.link.read, name)
        return int(round(value)) if is_int and math.isfinite(value) else value


async def run_configure(
    cfg: Config,
    opts: CheckOptions,
    confirm: Callable[[str], bool] = ask,
    show: Callable[[str], None] = print,
) -> ConfigureReport:
    """Plan, confirm, write, read back (refused while armed)."""
    target = await asyncio.to_thread(resolve_link, cfg, opts)
    link = ArduPilotLink(target.url, opts.timeout_s)
    await asyncio.to_thread(link.__enter__)
    session = ThreadedParamLink(link)
    try:
        armed = await session.armed()
        params = await session.params()
        status = await asyncio.to_thread(service_status, target.socket)
        refuse_if_armed(armed)
        seen = await asyncio.to_thread(link.watch, GPS_WATCH_S)
        ctx = context(cfg, opts, status, seen)
        head = header(link.url, link.system_id, link.autopilot, armed, len(params), ctx)

        def rows_of(values: dict[str, Param]) -> list[Row]:
            finite, not_finite = finite_params(values)
            return [*not_finite, *evaluate_rows(finite, ctx)]

        return await plan_and_write(session, head, params, rows_of, opts.yes, confirm, show)
    finally:
        link.close()

"""``companion autopilot configure`` on PX4 (``companion px4 configure``): write the values
check asks for, with the right types, through the shared flow
(:mod:`companion.autopilot.configure`).

MAVSDK writes each with its own type (``set_param_int`` for an INT32: its bits, never a float)
and reads each back.
"""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import Callable

from companion.autopilot.configure import (
    GPS_WATCH_S,
    ConfigureReport,
    ask,
    plan_and_write,
    refuse_if_armed,
)
from companion.autopilot.options import CheckOptions
from companion.autopilot.params import Param, Row
from companion.autopilot.px4.check import header, resolve
from companion.autopilot.px4.link import Px4Link
from companion.autopilot.px4.rules import evaluate
from companion.config import Config


async def run_configure(
    cfg: Config,
    opts: CheckOptions,
    confirm: Callable[[str], bool] = ask,
    show: Callable[[str], None] = print,
) -> ConfigureReport:
    """Plan, confirm, write, read back (refused while armed)."""
    target = await asyncio.to_thread(resolve, cfg, opts)  # a blocking socket read
    async with Px4Link(target.url, opts.timeout_s) as px4:
        armed = await px4.armed()
        params = await px4.params()
        head = header(px4.url, px4.system_id, px4.autopilot, armed, len(params), target.ctx)
        refuse_if_armed(armed)
        seen = await px4.watch(GPS_WATCH_S)
        ctx = dataclasses.replace(target.ctx, gps_seen=bool(seen["gps_seen"]))

        def rows_of(values: dict[str, Param]) -> list[Row]:
            return evaluate(values, ctx)

        return await plan_and_write(px4, head, params, rows_of, opts.yes, confirm, show)

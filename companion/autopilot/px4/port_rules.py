"""The PX4 parameters of the companion's MAVLink instance (pure): the instance on the
companion's port (MAV_n_CONFIG up to PX4 1.16; SER_<port>_PROT / MAV_ETH_EN after), a mode that
time-syncs, the serial rate or the UDP ports, and who speaks first on UDP."""

from __future__ import annotations

import re
from collections.abc import Mapping

from companion.autopilot.params import Judgement, Param, Row, Status, Target, labelled
from companion.autopilot.px4.link_context import LinkContext
from companion.autopilot.px4.typed_rows import int_row, int_value, needs_reboot

PORT_CODES = {"TELEM1": 101, "TELEM2": 102, "TELEM3": 103, "TELEM4": 104, "ETHERNET": 1000}
MIN_SERIAL_BAUD = 460800  # ODOMETRY at 30 Hz (~8 kB/s) + TIMESYNC + PX4's onboard streams
TIMESYNC_MODES = frozenset({2, 5, 8, 9, 11})  # MAV_n_MODEs whose streams include TIMESYNC
LOOPBACK_HOSTS = ("127.", "localhost", "::1")
# SER_<tag>_PROT ports in PX4's port order (firmware after 1.16 numbers MAVLink instances so)
PORT_TAGS = ("TEL1", "TEL2", "TEL3", "TEL4", "GPS1", "GPS2", "GPS3", "RC", "WIFI", "EXT2")
MAV_MODE = {
    0: "Normal",
    1: "Custom",
    2: "Onboard",
    3: "OSD",
    4: "Magic",
    5: "Config",
    7: "Minimal",
    8: "External Vision",
    10: "Gimbal",
    11: "Onboard Low Bandwidth",
    12: "uAvionix",
    13: "Low Bandwidth",
}
SERIAL_PORT = {
    0: "disabled",
    101: "TELEM 1",
    102: "TELEM 2",
    103: "TELEM 3",
    104: "TELEM/SERIAL 4",
    201: "GPS 1",
    202: "GPS 2",
    300: "Radio Controller",
    301: "Wifi",
    1000: "Ethernet",
}
BROADCAST = {0: "never", 1: "always", 2: "multicast only"}


def _uart_order(params: Mapping[str, Param]) -> dict[str, int]:
    """Firmware after PX4 1.16: SER_<tag>_PROT of each port, in PX4's port order."""
    prots: dict[str, int] = {}
    for name in params:
        m = re.fullmatch(r"SER_(\w+)_PROT", name)
        value = int_value(params, name, 0, 1000) if m else None
        if m and value is not None:
            prots[m.group(1)] = value
    rank = {t: i for i, t in enumerate(PORT_TAGS)}
    return dict(sorted(prots.items(), key=lambda kv: (rank.get(kv[0], len(rank)), kv[0])))


def _has_mav_config(params: Mapping[str, Param]) -> bool:
    return any(f"MAV_{i}_CONFIG" in params for i in range(3))


def _has_port_params(params: Mapping[str, Param]) -> bool:
    """The firmware assigns MAVLink instances to ports by parameters (MAV_n_CONFIG, or
    SER_<port>_PROT / MAV_ETH_EN after PX4 1.16). PX4 SITL has none of them: its start-up
    script starts each instance (``mavlink start -u 14580 -m onboard -o 14540``), and its
    MAV_n_* parameters are unused, so PX4 does not even list them over MAVLink."""
    return (
        _has_mav_config(params)
        or "MAV_ETH_EN" in params
        or any(re.fullmatch(r"SER_\w+_PROT", n) for n in params)
    )


def companion_instance(params: Mapping[str, Param], ctx: LinkContext) -> int | None:
    """The MAVLink instance that runs on the companion's port, or None (none runs there)."""
    if not _has_port_params(params):
        return None
    if _has_mav_config(params):
        code = PORT_CODES[ctx.fc_port]
        found = [i for i in range(3) if int_value(params, f"MAV_{i}_CONFIG", 0, 1000) == code]
        return found[0] if found else None
    uarts = [t for t, v in _uart_order(params).items() if v == 1]
    if ctx.fc_port == "ETHERNET":
        on = int_value(params, "MAV_ETH_EN", 0, 1) == 1
        return len(uarts) if on and len(uarts) < 3 else None
    tag = "TEL" + ctx.fc_port[-1]
    return uarts.index(tag) if tag in uarts and uarts.index(tag) < 3 else None


def _port_rows(params: Mapping[str, Param], ctx: LinkContext) -> tuple[int | None, list[Row]]:
    """The instance on the companion's port and its row(s): MAV_n_CONFIG (PX4 up to 1.16), or
    SER_<port>_PROT / MAV_ETH_EN (after 1.16, where MAVLink instances are numbered in port
    order, Ethernet's after the UARTs')."""
    code = PORT_CODES[ctx.fc_port]
    if not _has_port_params(params):
        return None, [
            Row(
                "MAVLink ports",
                "set by the start-up script",
                "-",
                "this firmware has no MAV_n_CONFIG, SER_<port>_PROT or MAV_ETH_EN (PX4 SITL: "
                "its start-up script starts each MAVLink instance with its ports and mode), so "
                "no parameter says which instance is the companion's; whether our messages "
                "arrive and PX4 time-syncs is watched below",
                Status.INFO,
            )
        ]
    if _has_mav_config(params):
        return _mav_config_port_rows(params, ctx, code)
    uarts = [t for t, v in _uart_order(params).items() if v == 1]
    if ctx.fc_port == "ETHERNET":
        return _ethernet_port_rows(params, uarts)
    return _uart_port_rows(params, ctx, uarts)


def _mav_config_port_rows(
    params: Mapping[str, Param], ctx: LinkContext, code: int
) -> tuple[int | None, list[Row]]:
    """PX4 up to 1.16: the MAV_n_CONFIG naming the companion's port, else a free instance."""
    configs = {i: int_value(params, f"MAV_{i}_CONFIG", 0, 1000) for i in range(3)}
    found = [i for i, c in configs.items() if c == code]
    if found:
        inst = found[0]
        return inst, [
            Row(
                f"MAV_{inst}_CONFIG",
                labelled(code, SERIAL_PORT),
                labelled(code, SERIAL_PORT),
                f"MAVLink instance {inst} runs on {ctx.fc_port}, where the companion is wired",
                Status.OK,
            )
        ]
    free = [i for i in (1, 2, 0) if configs.get(i) == 0]
    if not free:
        return None, [
            Row(
                "MAV_n_CONFIG",
                ", ".join(f"{i}: {configs[i]}" for i in range(3)),
                f"one instance on {ctx.fc_port}",
                "no MAVLink instance runs on the companion's port and none is free",
                Status.FAIL,
            )
        ]
    inst = free[0]
    name = f"MAV_{inst}_CONFIG"
    current = configs.get(inst)
    return inst, [
        Row(
            name,
            labelled(current, SERIAL_PORT) if current is not None else "missing",
            labelled(code, SERIAL_PORT),
            f"no MAVLink instance runs on {ctx.fc_port}, where the companion is wired "
            f"(instance {inst} is free)",
            Status.FAIL,
            (Target(name, code, True, True),),
        )
    ]


def _ethernet_port_rows(
    params: Mapping[str, Param], uarts: list[str]
) -> tuple[int | None, list[Row]]:
    """After PX4 1.16: MAV_ETH_EN, whose instance comes after the MAVLink UARTs (three at most)."""
    name = "MAV_ETH_EN"
    on = int_value(params, name, 0, 1)
    inst = len(uarts)
    if on is None or inst > 2:
        why = (
            "this firmware has neither MAV_n_CONFIG nor MAV_ETH_EN: no MAVLink on Ethernet"
            if on is None
            else f"all three MAVLink instances run on UARTs ({', '.join(uarts)})"
        )
        return None, [Row(name, str(on), "1 (on)", why, Status.FAIL)]
    why = (
        f"MAVLink on Ethernet runs as instance {inst}, after the {inst} MAVLink UART "
        "port(s) (PX4 after 1.16: MAV_ETH_EN replaced MAV_n_CONFIG = 1000)"
    )
    if on == 1:
        return inst, [Row(name, "1 (on)", "1 (on)", why, Status.OK)]
    return inst, [Row(name, "0 (off)", "1 (on)", why, Status.FAIL, (Target(name, 1, True, True),))]


def _uart_port_rows(
    params: Mapping[str, Param], ctx: LinkContext, uarts: list[str]
) -> tuple[int | None, list[Row]]:
    """After PX4 1.16: SER_<port>_PROT = MAVLink, its instance numbered in port order."""
    tag = "TEL" + ctx.fc_port[-1]
    name = f"SER_{tag}_PROT"
    prot = _uart_order(params).get(tag)
    if prot is None:
        why = "this firmware has neither MAV_n_CONFIG nor SER_<port>_PROT for this port"
        return None, [Row(name, "missing", "1 (MAVLink)", why, Status.FAIL)]
    rank = {t: i for i, t in enumerate(PORT_TAGS)}
    after = sorted({*uarts, tag}, key=lambda t: (rank.get(t, len(rank)), t))
    inst = after.index(tag)
    if inst > 2:
        why = f"MAVLink already runs on three ports before {tag} ({', '.join(uarts)})"
        return None, [Row(name, labelled(prot, {1: "MAVLink"}), "1 (MAVLink)", why, Status.FAIL)]
    why = f"MAVLink instance {inst} on {ctx.fc_port} (PX4 after 1.16 numbers them in port order)"
    if prot == 1:
        return inst, [Row(name, "1 (MAVLink)", "1 (MAVLink)", why, Status.OK)]
    return inst, [
        Row(
            name,
            str(prot),
            "1 (MAVLink)",
            f"{ctx.fc_port} runs another protocol; {why}",
            Status.FAIL,
            (Target(name, 1, True, True),),
        )
    ]


def _partner_row(params: Mapping[str, Param], ctx: LinkContext, inst: int, mode: int | None) -> Row:
    """Who speaks first on the companion's UDP link. PX4 on a flight controller (NuttX) sends
    on a UDP instance only to the address of the first packet it receives (its partner, kept
    until it reboots); before that it broadcasts, on MAV_n_REMOTE_PRT, only with
    MAV_n_BROADCAST = 1 and never in Onboard mode (mavlink_main.cpp). PX4 SITL (POSIX) sends
    to 127.0.0.1:MAV_n_REMOTE_PRT from the start, as the SITL stub does."""
    name = f"MAV_{inst}_BROADCAST"
    b = int_value(params, name, 0, 2)
    value = labelled(b, BROADCAST) if b is not None else "missing"
    udp_prt = int_value(params, f"MAV_{inst}_UDP_PRT", 1, 65535)
    udpout = f"udpout:<autopilot IP>:{udp_prt if udp_prt is not None else '<MAV_n_UDP_PRT>'}"
    if ctx.link_host.startswith(LOOPBACK_HOSTS):
        return Row(
            name,
            value,
            "any (same host)",
            "the service and PX4 share a host (SITL): PX4's POSIX build sends to "
            f"127.0.0.1:MAV_{inst}_REMOTE_PRT from the start, so either side may speak first",
            Status.OK,
        )
    if ctx.link_kind == "udpout":
        return Row(
            name,
            value,
            "any (the service speaks first)",
            "the service sends first and PX4 takes it as its partner (address and port) until "
            "it reboots: the service sends from an ephemeral port, so after a restart of the "
            "service PX4 streams to the old one (no ATTITUDE, DISTANCE_SENSOR, TIMESYNC): "
            "reboot the autopilot after restarting the service",
            Status.WARN,
        )
    broadcasts = b == 1 and mode is not None and mode != 2
    if broadcasts and ctx.link_host in ("0.0.0.0", ""):
        return Row(
            name,
            value,
            "1 (always), not in Onboard mode",
            f"PX4 broadcasts on MAV_{inst}_REMOTE_PRT until a partner speaks; the service "
            f"listens on {ctx.link_host}:{ctx.link_port}, answers, and becomes the partner",
            Status.OK,
        )
    target: tuple[Target, ...] = ()
    if mode in (8, 11) and b == 0 and ctx.link_host in ("0.0.0.0", ""):
        target = (Target(name, 1, True, needs_reboot(name)),)
    return Row(
        name,
        value,
        f"the service to send first ({udpout})",
        "PX4 on the flight controller sends on this instance only to the address of the first "
        "packet it receives, and broadcasts only with MAV_n_BROADCAST = 1 and never in "
        f"Onboard mode: the listening service (udpin:{ctx.link_host}:{ctx.link_port}) and PX4 "
        f"wait for each other. Make the service speak first: service.mavlink_url = {udpout}"
        + (" (or broadcast: 1 here, the service on 0.0.0.0)" if target else ""),
        Status.FAIL,
        target,
    )


def link_rows(params: Mapping[str, Param], ctx: LinkContext) -> list[Row]:
    """The MAVLink instance on the companion's port: enabled there, a mode that time-syncs,
    the same rate, UDP ports and who speaks first."""
    inst, rows = _port_rows(params, ctx)
    if inst is None:
        return rows
    mode = int_value(params, f"MAV_{inst}_MODE", 0, 13)
    rows.append(int_row(params, f"MAV_{inst}_MODE", 0, 13, _judge_mode, MAV_MODE))
    if ctx.fc_port == "ETHERNET":
        rows += _udp_rows(params, ctx, inst, mode)
    else:
        rows.append(_baud_row(params, ctx))
    rows += _other_link_rows(params, inst)
    return rows


def _judge_mode(v: int) -> Judgement:
    """MAV_n_MODE: a mode that streams TIMESYNC, so PX4 moves our stamps into its clock."""
    need = "2 (Onboard)"
    if v == 2:
        why = "Onboard: companion-rate streams, and TIMESYNC at 10 Hz, so PX4 moves our "
        why += "stamps into its clock"
        return Judgement(Status.OK, need, why)
    if v == 8:
        why = "External Vision: TIMESYNC at 10 Hz and the streams a VIO needs"
        return Judgement(Status.OK, need, why)
    if v == 11:
        why = "Onboard Low Bandwidth: TIMESYNC at 10 Hz with fewer streams (right on a slow "
        why += "serial link)"
        return Judgement(Status.OK, need, why)
    if v in TIMESYNC_MODES:
        why = f"{MAV_MODE.get(v, v)} mode time-syncs, but streams for another peer"
        return Judgement(Status.WARN, need, why, 2)
    return Judgement(
        Status.WARN,
        need,
        f"{MAV_MODE.get(v, v)} mode streams no TIMESYNC: PX4 still fuses our messages but "
        "stamps them at arrival (latency not compensated), at ground-station stream rates",
        2,
    )


def _udp_rows(
    params: Mapping[str, Param], ctx: LinkContext, inst: int, mode: int | None
) -> list[Row]:
    """Ethernet over UDP: PX4's port matches the service's, and who speaks first."""
    if ctx.link_kind not in ("udpin", "udpout"):
        return []
    key = "REMOTE_PRT" if ctx.link_kind == "udpin" else "UDP_PRT"
    what = "sends to" if ctx.link_kind == "udpin" else "listens on"

    def port_judge(v: int) -> Judgement:
        why = f"PX4 {what} this UDP port; the service uses {ctx.link_port}"
        status = Status.OK if v == ctx.link_port else Status.FAIL
        return Judgement(status, str(ctx.link_port), why, ctx.link_port)

    return [
        int_row(params, f"MAV_{inst}_{key}", 1, 65535, port_judge),
        _partner_row(params, ctx, inst, mode),
    ]


def _baud_row(params: Mapping[str, Param], ctx: LinkContext) -> Row:
    """A serial port: SER_TELn_BAUD at the service's rate, and fast enough for our streams."""
    tel = ctx.fc_port[-1]
    serial = ctx.link_kind == "serial"

    def baud_judge(v: int) -> Judgement:
        want = ctx.link_port if serial else 921600
        why = "both ends of the wire at the same rate"
        if v == 0:
            return Judgement(
                Status.WARN,
                str(want),
                f"0 = Auto: PX4 chooses the rate; set the service's {want} so that both ends "
                "surely match",
                want,
            )
        if serial and v != want:
            return Judgement(Status.FAIL, str(want), f"{why}; the service uses {want}", want)
        if v < MIN_SERIAL_BAUD:
            return Judgement(
                Status.WARN,
                f">= {MIN_SERIAL_BAUD}",
                "too slow for 30 Hz ODOMETRY plus TIMESYNC and PX4's onboard streams",
            )
        return Judgement(Status.OK, str(want), why)

    return int_row(params, f"SER_TEL{tel}_BAUD", 0, 3_000_000, baud_judge, {0: "Auto"})


def _other_link_rows(params: Mapping[str, Param], inst: int) -> list[Row]:
    """The other MAVLink instances with a port (MAV_n_CONFIG): context, not ours."""
    rows = []
    for i in range(3):
        c = int_value(params, f"MAV_{i}_CONFIG", 0, 1000)
        if i != inst and c:
            other = int_value(params, f"MAV_{i}_MODE", 0, 13)
            rows.append(
                Row(
                    f"MAV_{i}_CONFIG",
                    labelled(c, SERIAL_PORT),
                    "-",
                    f"another MAVLink link ({MAV_MODE.get(other or 0, other)} mode): not ours",
                    Status.INFO,
                )
            )
    return rows

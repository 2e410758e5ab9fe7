"""The service's commands: ``companion run | status | config``."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion.cli.common import EXIT_NOT_RUNNING, EXIT_OK, json_error, load
from companion.drivers.status import find_status_socket, json_safe, printable_status, read_status

if TYPE_CHECKING:  # `companion status` starts without NumPy (tests/companion/cli/test_cli.py)
    from companion.config import Config


def cmd_config(args: argparse.Namespace) -> int:
    """Print every option with its value and help, after the checks `run` makes before it
    starts (files, URLs, the status socket path): a file that passes here starts there."""
    from companion.config import describe
    from companion.errors import ConfigError, DatasetError
    from companion.service import preflight

    cfg = load(args)
    check_path_keys(cfg)
    try:
        warnings = preflight.check(cfg)
    except DatasetError as e:  # folder:PATH on a dataset the reader refuses
        raise ConfigError(f"service.camera_url: {e}") from None
    print("\n".join(describe(cfg)))
    for text in warnings:
        print(f"companion: warning: {text}", file=sys.stderr)
    return EXIT_OK


def path_keys(cfg: Config) -> list[tuple[str, Path]]:
    """The files the service reads or writes by the config's path keys (set ones only)."""
    from companion.drivers.signing import default_timestamp_file
    from companion.service.state import RESET_COUNTER_FILE, state_dir

    o = cfg.service
    keys = [
        ("service.signing.key_file", o.signing.key_file),
        ("service.mqtt.ca_file", o.mqtt.ca_file),
        ("service.report_path", o.report_path),
    ]
    paths = [(key, Path(value)) for key, value in keys if value]
    if o.signing.key_file:
        paths.append(("service.signing.timestamp_file", default_timestamp_file(o.signing)))
    paths.append(("service.state_dir", state_dir(o.state_dir) / RESET_COUNTER_FILE))
    return paths


def check_path_keys(cfg: Config) -> None:
    """ConfigError naming the key whose file is there but is not a regular file (a FIFO, a
    device, a socket, a folder): reading one would block or never end. Checked by name,
    nothing is opened."""
    import os
    import stat

    from companion.bounded import file_kind
    from companion.errors import ConfigError

    for key, path in path_keys(cfg):
        try:
            mode = os.stat(path).st_mode
        except (OSError, ValueError):
            continue  # not there (yet): the checks that follow say whether that is fine
        if not stat.S_ISREG(mode):
            raise ConfigError(f"{key}: {path} is {file_kind(mode)}, not a regular file")


def cmd_run(args: argparse.Namespace) -> int:
    """The service: camera + rangefinders + autopilot link -> pose messages, until SIGTERM /
    SIGINT or --duration."""
    import asyncio

    from companion.config import describe
    from companion.redact import redact_url

    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    log = logging.getLogger("companion")
    cfg = load(args)
    check_path_keys(cfg)  # a FIFO state or timestamp file would block the start forever
    if args.web is not None:  # --web [HOST:]PORT: the live page there, checked as [web] is
        cfg = with_web(cfg, args.web)
    if args.record is not None:  # --record DIR: the [record] options, into this folder
        import dataclasses

        cfg = dataclasses.replace(cfg, record=dataclasses.replace(cfg.record, dir=str(args.record)))
    for line in describe(cfg):
        log.debug("config %s", line)
    s = cfg.service
    log.info("link %s, camera %s, output %s", s.mavlink_url, redact_url(s.camera_url), s.output)
    report = args.report or s.report_path
    summary = asyncio.run(_serve(cfg, args.duration, report, log))
    log.info(
        "published %d poses (%.1f Hz), %d frames in, %d dropped, latency p50 %s ms",
        summary["published"],
        summary["publish_rate_hz"],
        summary["frames_in"],
        summary["frames_dropped"],
        f"{summary['latency_ms_p50']:.1f}" if summary["latency_ms_p50"] is not None else "-",
    )
    return EXIT_OK


def with_web(cfg: Config, flag: str) -> Config:
    """``cfg`` with the live page on at ``--web [HOST:]PORT`` (the rest of [web] kept); a
    ConfigError naming ``--web`` or the [web] key (a Wi-Fi address without web.token)."""
    import dataclasses

    from companion.config import from_dict, to_dict
    from companion.service_options import WebOptions, web_flag

    web = from_dict(WebOptions, {**to_dict(cfg.web), **web_flag(flag)}, "web.")
    return dataclasses.replace(cfg, web=web)


async def _serve(
    cfg: Config, duration: float | None, report: Path | str | None, log: logging.Logger
) -> dict[str, Any]:
    """Run the service until stopped; write the exit report; return its summary."""
    import asyncio
    import signal

    from companion.service.app import Service

    service = Service(cfg)  # a bad URL raises ConfigError here, before anything starts
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, service.stop)
    async with service:
        await service.run(duration)
    summary = service.summary()
    if report:
        try:
            service.write_report(Path(report))
        except OSError as e:  # a full disk: the run itself went fine
            log.warning("exit report not written to %s: %s", report, e)
    return summary


def cmd_status(args: argparse.Namespace) -> int:
    """Show the running service's state (exit 3 when it is not running). The socket: --socket,
    else service.status_socket of --config, else where the service runs (drivers.status:
    /run/companion/status.sock under systemd, else the per-user path)."""
    configured = str(args.socket or "") or (load(args).service.status_socket if args.config else "")
    path = find_status_socket(configured)
    while True:
        st = read_status(path)
        if st is None:
            text = f"companion is not running (no service on {path})"
            if args.json:
                text = json_error(text, EXIT_NOT_RUNNING, "not running", socket=str(path))
            print(text, flush=True)
            return EXIT_NOT_RUNNING
        # JSON escapes control characters itself; the table prints them made printable
        text = (
            json.dumps(json_safe(st), indent=2)
            if args.json
            else format_status(printable_status(st))
        )
        if args.watch:
            print("\033[H\033[2J" + text, flush=True)
            time.sleep(1.0)
            continue
        print(text)
        return EXIT_OK


# ------------------------------------------------------------------------------ status table
def _fmt(v: Any, unit: str = "", digits: int = 2) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}{unit}"
    return f"{v}{unit}"


def _mqtt_line(m: dict[str, Any]) -> str:
    if not m.get("enabled"):
        return "disabled"
    state = "connected" if m.get("connected") else "NOT connected"
    return f"{state}, {m.get('queued', 0)} queued, {m.get('dropped', 0)} dropped"


def _web_line(w: dict[str, Any]) -> str:
    """The live page: where, and who watches (or why it is off)."""
    if not w.get("enabled"):
        return "disabled"
    if not w.get("listening", True):
        return f"OFF: {w.get('problem') or 'not listening'}"
    return f"{w.get('url', '-')}  {w.get('viewers', 0)} viewer(s)"


def _signing_text(ap: dict[str, Any]) -> str:
    sg = ap.get("signing")
    if not sg:
        return ", unsigned link"
    far = f", {sg['far_ahead']} stamped too far ahead" if sg.get("far_ahead") else ""
    return (
        f", signed: {sg.get('good_signatures', 0)} good, {sg.get('bad_signatures', 0)} bad "
        f"signatures, {sg.get('refused', 0)} refused{far}"
    )


def _autopilot_rows(ap: dict[str, Any]) -> list[tuple[str, str]]:
    return [
        (
            "autopilot",
            f"{ap['url']}  system {_fmt(ap['system_id'])}  heartbeat "
            f"{_fmt(ap['heartbeat_age_s'], ' s ago', 1)}",
        ),
        (
            "  time sync",
            f"{'converged' if ap['timesync_converged'] else 'NOT converged'}  "
            f"offset {_fmt(ap['timesync_offset_ms'], ' ms', 3)}  "
            f"rtt {_fmt(ap['timesync_rtt_ms'], ' ms', 2)}" + _px4_stamps_text(ap),
        ),
        ("  messages", f"{ap['rx_messages']} in, {ap['rx_bad']} bad" + _signing_text(ap)),
    ]


def _px4_stamps_text(ap: dict[str, Any]) -> str:
    """PX4's side of the time sync as the service models it (newer services only)."""
    converts = ap.get("px4_converts_stamps")
    if converts is None:
        return ""
    if converts:
        return "  PX4 converts our stamps"
    return f"  PX4 stamps on arrival: poses sent as of sending ({ap.get('stamped_at_send', 0)})"


def _camera_text(cam: dict[str, Any]) -> str:
    return (
        f"{cam['url']}  {_fmt(cam['fps'], ' fps', 1)}  {cam['frames']} frames, "
        f"{cam['dropped']} dropped, last {_fmt(cam['last_frame_age_s'], ' s ago', 2)}"
        + (f", stamped at {cam['stamps']}" if cam.get("stamps") in ("grab", "v4l2 buffer") else "")
        + (f"  NOW {cam['problem'].upper()} FRAMES" if cam.get("problem") else "")
        + "".join(f", {n} {k}" for k, n in (cam.get("rejected") or {}).items())
    )


def _camera_check(vo: dict[str, Any]) -> str:
    """The camera's clock and lens (focal length, k1) as the pipeline checks them in flight."""
    clock = "stamps steady"
    if vo.get("frames_retimed"):
        clock = (
            f"stamps jitter {_fmt(vo.get('stamp_jitter_ms'), ' ms', 1)} rms: "
            f"{vo['frames_retimed']} frames re-timed"
        )
    pairs = vo.get("focal_pairs") or 0
    k1 = f", k1 {vo['k1_delta']:+.3f}" if vo.get("k1_delta") is not None else ""
    focal = f"focal x{vo['focal_ratio']:.3f}{k1} over {pairs} pairs" if pairs else "lens unchecked"
    if vo.get("lens_learned"):
        fx, fy, k1_now = vo["lens_learned"]
        focal += f" (learned fx {fx:.1f}, fy {fy:.1f}, k1 {k1_now:.3f})"
    return f"{clock}  {focal}" + (f"  {vo['lens_warning']}" if vo.get("lens_warning") else "")


def _gate_rows(sc: dict[str, Any]) -> list[tuple[str, str]]:
    """The scale filter's row when it has been gated out for over a second or restarted (a
    status from a service without these keys: none)."""
    outside_s, restarts = sc.get("outside_gate_s") or 0.0, sc.get("recoveries") or 0
    if outside_s < 1.0 and not restarts:
        return []
    text = f"every measurement outside its gate for {outside_s:.1f} s" if outside_s >= 1.0 else ""
    if restarts:
        text += f"{'; ' if text else ''}restarted at them {restarts} time(s)"
    return [("  filter", text)]


def _estimate_rows(st: dict[str, Any]) -> list[tuple[str, str]]:
    vo, sc, att, out = st["vo"], st["scale"], st["attitude"], st["output"]
    matches = (sc.get("match_rate") or {}).items()
    return [
        (
            "VO",
            f"{vo['state']}  {vo['features']} features  {vo['keyframes']} keyframes  "
            f"{vo['resets']} resets",
        ),
        (
            "scale",
            f"{sc['method']}  {_fmt(sc['value'], '', 4)} ± {_fmt(sc['sigma'], '', 4)}  "
            f"{sc['sensors_used']} sensors  ranges {sc['ranges_in']} in, "
            f"{sc['ranges_rejected']} rejected",
        ),
        ("  matches", "  ".join(f"sensor {k} {100 * v:.0f} %" for k, v in matches) or "-"),
        *_gate_rows(sc),
        ("camera check", _camera_check(vo)),
        (
            "roll/pitch",
            f"{_fmt(att['roll_deg'], '°')} / {_fmt(att['pitch_deg'], '°')}  "
            f"± {_fmt(att['sigma_deg'], '°', 3)}  "
            f"compensation {'on' if att['compensation'] else 'off'}",
        ),
        (
            "output",
            f"{out['message']}  {_fmt(out['rate_hz'], ' Hz', 1)}  {out['published']} sent  "
            f"reset_counter {out['reset_counter']}  "
            f"latency p50 {_fmt(out['latency_ms_p50'], ' ms', 1)}",
        ),
    ]


def _frame_line(fr: dict[str, Any]) -> str:
    """[gps] align: the output's frame, its agreement with GPS, the alignment, the verdict."""
    if not fr.get("enabled"):
        return "own (gps.align off)"
    gps = fr["gps"]
    verdict = "good" if gps["good"] else "bad: " + "; ".join(gps["reasons"][:2])
    t = fr["translation_ned_m"]
    return (
        f"{fr['state']}  agree {_fmt(fr['agreement_m'], ' m', 2)}  yaw {fr['yaw_deg']:.2f}°  "
        f"t ({t[0]:.2f}, {t[1]:.2f}, {t[2]:.2f}) m  fit age {_fmt(fr['age_s'], ' s', 1)}  "
        f"GPS {verdict}"
    )


def format_status(st: dict[str, Any]) -> str:
    """The status JSON as a readable table (plain text, aligned)."""
    rows = [
        ("uptime", _fmt(st["uptime_s"], " s", 0)),
        *_autopilot_rows(st["autopilot"]),
        ("camera", _camera_text(st["camera"])),
        *_estimate_rows(st),
        ("MQTT", _mqtt_line(st["mqtt"])),
        ("web", _web_line(st.get("web") or {"enabled": False})),
        ("frame", _frame_line(st.get("frame") or {"enabled": False})),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"{k:<{width}}  {v}" for k, v in rows]
    warnings = st.get("warnings") or []
    lines.append(f"{'warnings':<{width}}  " + ("none" if not warnings else warnings[-1]))
    lines.extend(f"{'':<{width}}  {w}" for w in warnings[-5:-1][::-1])
    for r in st["attitude"].get("reasons", [])[:3]:
        lines.append(f"{'':<{width}}  roll/pitch: {r}")
    return "\n".join(lines)


# ------------------------------------------------------------------------------ parsers
def add_config(sub: Any) -> None:
    """``companion config``."""
    p_cfg = sub.add_parser("config", help="print the effective configuration")
    p_cfg.add_argument("--config", type=Path, help="TOML config file (default: built-in SITL)")
    p_cfg.set_defaults(func=cmd_config)


def add_run(sub: Any) -> None:
    """``companion run``."""
    p_run = sub.add_parser("run", help="the service (camera + rangefinders -> autopilot)")
    p_run.add_argument("--config", type=Path, help="TOML config file (default: built-in SITL)")
    p_run.add_argument("--duration", type=float, help="stop after this many seconds")
    p_run.add_argument("--report", type=Path, help="write a JSON summary here on exit")
    p_run.add_argument(
        "--record",
        type=Path,
        metavar="DIR",
        help="record what the pipeline is fed into the new file DIR.mcap ({start}: the start "
        "time; record.format = 'folder': the new folder DIR); `companion eval DIR.mcap` "
        "replays it ([record] in the config: budget, format, image)",
    )
    p_run.add_argument(
        "--web",
        metavar="[HOST:]PORT",
        help="serve the live page on PORT (HOST: 127.0.0.1; another address needs web.token "
        'in the config); docs/service.md, "The live page"',
    )
    p_run.add_argument("--terrain", help=argparse.SUPPRESS)
    p_run.add_argument("--trajectory", help=argparse.SUPPRESS)
    p_run.add_argument("--seconds", type=float, help=argparse.SUPPRESS)
    p_run.add_argument("--seed", type=int, help=argparse.SUPPRESS)
    p_run.set_defaults(func=cmd_run)


def add_status(sub: Any) -> None:
    """``companion status``."""
    p_status = sub.add_parser("status", help="the running service's state (exit 3 if none)")
    p_status.add_argument("--config", type=Path, help="TOML config (for service.status_socket)")
    p_status.add_argument(
        "--socket",
        type=Path,
        help="status socket path (default: /run/companion/status.sock if there, else per user)",
    )
    p_status.add_argument("--json", action="store_true", help="JSON for machines (errors too)")
    p_status.add_argument("--watch", action="store_true", help="refresh every second")
    p_status.set_defaults(func=cmd_status)

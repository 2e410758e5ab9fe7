"""What the command modules share: exit codes, the config with the SITL flags' overrides, the
SITL flags themselves, run names, output folders, progress bars and option-dataclass flags.

Light on purpose (``companion --help`` and ``companion status`` import it): the config (NumPy)
and tqdm are imported by the functions that use them."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import signal
import sys
import threading
import time
import typing
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

if TYPE_CHECKING:
    from companion.config import Config, SitlConfig

# Exit codes of every command (docs/service.md, "Exit codes"; `companion --help` lists them)
EXIT_OK = 0
EXIT_PROBLEMS = 1  # problems found (px4 check, calibrate lasers), or the command failed
EXIT_USAGE = 2  # bad arguments, configuration or input file (the message names flag, key or file)
EXIT_UNREACHABLE = 3  # no service on the status socket / no autopilot on the link
EXIT_INTERRUPTED = 130  # SIGINT (128 + 2)
EXIT_BROKEN_PIPE = 141  # stdout closed by the reader (`companion config | head`): 128 + SIGPIPE
EXIT_ERROR, EXIT_CONFIG, EXIT_NOT_RUNNING = EXIT_PROBLEMS, EXIT_USAGE, EXIT_UNREACHABLE
EXIT_CODES: tuple[tuple[int, str], ...] = (
    (EXIT_OK, "ok"),
    (EXIT_PROBLEMS, "problems found (px4 check, calibrate lasers) or the command failed"),
    (EXIT_USAGE, "bad arguments, configuration or dataset (the message names flag, key or file)"),
    (EXIT_UNREACHABLE, "no service answers on the status socket, or no autopilot on the link"),
    (EXIT_INTERRUPTED, "interrupted (SIGINT)"),
    (EXIT_BROKEN_PIPE, "the reader closed stdout (as a program killed by SIGPIPE)"),
)


def json_error(message: str, exit_code: int, kind: str, **extra: Any) -> str:
    """The one-line JSON object a command given ``--json`` prints instead of a text error:
    ``{"error": message, "exit_code": n, "kind": kind, ...extra}``."""
    return json.dumps({"error": message, "exit_code": exit_code, "kind": kind, **extra})


DPOSE_ARM_S = 1.0  # d-Pose runs: the marks are painted (and d-Pose armed) at this time [s]

T = TypeVar("T")


def sitl_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """CLI flags -> nested config overrides (only the flags the user gave)."""
    sitl: dict[str, Any] = {}
    for flag, key in (
        ("terrain", "terrain"),
        ("trajectory", "trajectory"),
        ("seed", "seed"),
        ("seconds", "seconds"),
        ("altitude", "altitude_m"),
        ("speed", "speed_m_s"),
    ):
        value = getattr(args, flag, None)
        if value is not None:
            sitl[key] = value
    if getattr(args, "takeoff_landing", False):
        sitl["takeoff_landing"] = True
    if getattr(args, "laser_marks", None) is not None:
        sitl["render"] = {"laser_marks": args.laser_marks}
    return {"sitl": sitl} if sitl else {}


def load(args: argparse.Namespace) -> Config:
    """The config of ``--config`` (default: the built-in SITL one) with the SITL flags."""
    from companion.config import load_config

    return load_config(getattr(args, "config", None), sitl_overrides(args))


def dpose_config(args: argparse.Namespace) -> Config:
    """The SITL config of a d-Pose run: the four d-Pose lasers, marks painted at DPOSE_ARM_S,
    the spiral flight unless another trajectory is asked for."""
    from companion.config import dpose_rangefinders, load_config

    overrides = sitl_overrides(args)
    overrides.setdefault("sitl", {}).setdefault("trajectory", "spiral")
    cfg = load_config(getattr(args, "config", None), overrides)
    render = dataclasses.replace(cfg.sitl.render, laser_marks="painted", painted_time_s=DPOSE_ARM_S)
    return dataclasses.replace(
        cfg,
        rangefinders=dpose_rangefinders(),
        sitl=dataclasses.replace(cfg.sitl, render=render),
    )


def add_sitl_flags(p: argparse.ArgumentParser) -> None:
    """The flags that choose a simulated flight (--terrain, --seconds, ...)."""
    p.add_argument("--config", type=Path, help="TOML config file (default: built-in SITL)")
    p.add_argument(
        "--terrain",
        choices=["flat", "hills", "urban", "slope"],
        help="simulated ground (default hills)",
    )
    p.add_argument(
        "--trajectory",
        choices=["hover", "circle", "lawnmower", "figure8", "climb"],
        help="flight path (default lawnmower)",
    )
    p.add_argument("--seconds", type=float, help="flight duration [s]")
    p.add_argument("--seed", type=int, help="seed of terrain, noise and faults (default 1)")
    p.add_argument("--altitude", type=float, help="height above ground [m] (0 = terrain default)")
    p.add_argument("--speed", type=float, help="cruise speed [m/s]")
    p.add_argument("--takeoff-landing", action="store_true", help="take off and land")
    p.add_argument(
        "--laser-marks",
        choices=["off", "live", "painted"],
        help="laser dots in the image: off, live (move) or painted (stay); default live",
    )


def run_name(s: SitlConfig) -> str:
    """The name of a simulated flight, e.g. ``sitl-hills-lawnmower-60s-seed1``."""
    return f"sitl-{s.terrain}-{s.trajectory}-{s.seconds:g}s-seed{s.seed}"


def out_dir(args: argparse.Namespace, default: Path) -> Path:
    """``--out`` or ``default``, created."""
    out = Path(args.out) if args.out else default
    out.mkdir(parents=True, exist_ok=True)
    return out


@contextmanager
def progress(total: int, desc: str, enabled: bool) -> Iterator[Iterator[None]]:
    """A progress bar on stderr over ``total`` frames; yields the ticks to advance it."""
    from tqdm import tqdm

    bar = tqdm(
        total=total,
        unit="frame",
        desc=desc,
        file=sys.stderr,
        disable=not enabled,
        dynamic_ncols=True,
    )

    def ticks() -> Iterator[None]:
        while True:
            bar.update(1)
            yield None

    try:
        yield ticks()
    finally:
        bar.close()


def exit_on_sigterm() -> None:
    """SIGTERM ends the command through SystemExit, so that ``finally`` blocks run (the SITL
    camera process and the soak's service are stopped, not orphaned on their ports)."""

    def stop(signum: int, _frame: Any) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, stop)


def add_option_flags(p: argparse.ArgumentParser, cls: type[Any]) -> None:
    """One flag per field of the options dataclass ``cls``, help and default from the field."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        flag = "--" + f.name.replace("_", "-")
        text = f"{f.metadata.get('help', '')} (default {f.default})"
        if hints[f.name] is bool:
            p.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=text)
        else:
            p.add_argument(flag, type=hints[f.name], default=None, metavar="N", help=text)


def options(args: argparse.Namespace, cls: type[T]) -> T:
    """The options dataclass from the flags the user gave (bounds checked: ConfigError)."""
    from companion.config import from_dict

    assert dataclasses.is_dataclass(cls)
    given = {
        f.name: getattr(args, f.name)
        for f in dataclasses.fields(cls)
        if getattr(args, f.name, None) is not None
    }
    return from_dict(cls, given)


# ------------------------------------------------------------------------------ budgets
DEFAULT_MAX_MEMORY_MB = 2048.0  # half a 4 GB board: the OS and the service keep the rest
DEFAULT_TIMEOUT_S = 4 * 3600.0  # an hour of flight replays in well under this on a Pi 4
BUDGET_POLL_S = 0.05  # how often the watchdog looks at the resident memory and the clock
BUDGET_GRACE_S = 5.0  # after the interrupt, how long the command may take to end by itself


BUDGET_SIGNAL = signal.SIGUSR1  # how the watchdog interrupts the main thread


class BudgetExceeded(BaseException):
    """Raised in the main thread when the watchdog finds the budget exceeded (a BaseException:
    no ``except Exception`` on the way swallows it)."""


@dataclasses.dataclass
class Budget:
    """What an unattended command may use: resident memory [MB] and wall time [s] (0: no
    limit); ``exceeded``: why the watchdog stopped it (empty while within)."""

    max_memory_mb: float
    timeout_s: float
    exceeded: str = ""
    peak_mb: float = 0.0


def add_budget_flags(p: argparse.ArgumentParser) -> None:
    """--max-memory-mb and --timeout-s (the command fails cleanly with exit 2 beyond them)."""
    p.add_argument(
        "--max-memory-mb",
        type=float,
        default=DEFAULT_MAX_MEMORY_MB,
        help=f"stop with exit 2 above this resident memory [MB] (default "
        f"{DEFAULT_MAX_MEMORY_MB:g}: fits a 4 GB board; 0 = no limit)",
    )
    p.add_argument(
        "--timeout-s",
        type=float,
        default=DEFAULT_TIMEOUT_S,
        help=f"stop with exit 2 after this long [s] (default {DEFAULT_TIMEOUT_S:g}; 0 = none)",
    )


def resident_mb() -> float:
    """This process's resident memory now [MB] (Linux /proc; elsewhere its peak)."""
    try:
        with open("/proc/self/statm", "rb") as fh:
            pages = int(fh.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def mapped_mb() -> float:
    """This process's address space now [MB] (Linux /proc; 0 elsewhere)."""
    try:
        with open("/proc/self/statm", "rb") as fh:
            return int(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return 0.0


@contextmanager
def resource_budget(max_memory_mb: float, timeout_s: float) -> Iterator[Budget]:
    """Hold the block to a memory and time budget. A watchdog thread polls the resident
    memory and the clock; past either it interrupts the main thread (BudgetExceeded, with
    ``Budget.exceeded`` saying why: the command turns it into exit 2) and, should the main
    thread be stuck in C code, ends the process with exit 2 after BUDGET_GRACE_S. The address
    space is also capped at what is mapped now plus twice the memory budget (RLIMIT_AS,
    restored after), so that one enormous allocation fails at once (MemoryError) instead of
    swapping the machine before the watchdog sees it."""
    if not math.isfinite(max_memory_mb) or not math.isfinite(timeout_s):
        raise ValueError("--max-memory-mb and --timeout-s must be finite")
    budget = Budget(max(0.0, max_memory_mb), max(0.0, timeout_s))
    done = threading.Event()
    watchdog = threading.Thread(target=_watch, args=(budget, done), daemon=True)
    restore = _cap_address_space(budget.max_memory_mb and mapped_mb() + 2 * budget.max_memory_mb)
    in_main = threading.current_thread() is threading.main_thread()  # else: _exit alone
    previous = signal.signal(BUDGET_SIGNAL, _raise_exceeded) if in_main else None
    watchdog.start()
    try:
        yield budget
    finally:
        done.set()
        watchdog.join()
        if in_main:
            signal.signal(BUDGET_SIGNAL, previous)
        restore()


def _raise_exceeded(_signum: int, _frame: Any) -> None:
    raise BudgetExceeded()


def _watch(budget: Budget, done: threading.Event) -> None:
    """The watchdog of :func:`resource_budget`."""
    main_thread = threading.main_thread().ident
    assert main_thread is not None
    start = time.monotonic()
    while not done.wait(BUDGET_POLL_S):
        rss = resident_mb()
        budget.peak_mb = max(budget.peak_mb, rss)
        elapsed = time.monotonic() - start
        if budget.max_memory_mb and rss > budget.max_memory_mb:
            budget.exceeded = (
                f"resident memory {rss:.0f} MB above --max-memory-mb {budget.max_memory_mb:g}"
            )
        elif budget.timeout_s and elapsed > budget.timeout_s:
            budget.exceeded = f"still running after --timeout-s {budget.timeout_s:g} s"
        if budget.exceeded:
            if signal.getsignal(BUDGET_SIGNAL) is _raise_exceeded:
                signal.pthread_kill(main_thread, BUDGET_SIGNAL)  # also ends a blocking syscall
            if not done.wait(BUDGET_GRACE_S):
                os.write(2, f"companion: budget exceeded: {budget.exceeded}\n".encode())
                os._exit(EXIT_USAGE)
            return


def _cap_address_space(limit_mb: float) -> Callable[[], None]:
    """Lower RLIMIT_AS's soft limit to ``limit_mb`` (0: leave it); returns what restores it."""
    try:
        import resource
    except ImportError:  # not a Unix
        return lambda: None
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    want = int(limit_mb * 2**20)
    if not want or (hard != resource.RLIM_INFINITY and want > hard):
        return lambda: None
    if soft != resource.RLIM_INFINITY and soft <= want:
        return lambda: None
    resource.setrlimit(resource.RLIMIT_AS, (want, hard))
    return lambda: resource.setrlimit(resource.RLIMIT_AS, (soft, hard))

"""Command line of ``companion``: the service, evaluation, benchmarks, the simulator, tools.

One module per group of commands; each parses its arguments and calls functions elsewhere:

- :mod:`.service`: ``run``, ``status``, ``config``
- :mod:`.evaluate`: ``eval``, ``report``; :mod:`.evaluate_dpose` (``eval --dpose``) and
  :mod:`.flight` (``eval --phases``: the published poses by flight phase) beside it
- :mod:`.results`: ``results`` (the tables of docs/RESULTS.md from one batch, serial or on
  Ray) and ``sweep`` (a grid of config values over datasets or flights); the batch itself is
  :mod:`companion.batch`
- :mod:`.replay`: ``replay`` (flight recordings through this version) and ``compare`` (two
  replays side by side)
- :mod:`.dataset`: ``dataset import | rebuild`` (real sequences into our format)
- :mod:`.bench`: ``bench render | vo | attitude | dpose | soak``
- :mod:`.sim`: ``sitl record | sheet | run | px4``, ``demo``; and the one place where the
  product reaches the simulator (``sitl``): the other modules get simulated flights from it
- :mod:`.calibrate`: ``calibrate board | intrinsics | lasers | sim-board | sim-lasers``
- :mod:`companion.autopilot.cli`: ``autopilot check | configure`` (PX4 or ArduPilot, from its
  HEARTBEAT) and its PX4 alias ``px4 check | configure``
- :mod:`.common`: exit codes, the config with the SITL flags, run names, progress bars

Start-up is lazy (docs/BENCHMARKS.md, "CLI start-up"): :data:`COMMANDS` names each command,
its one-line help and the module that defines its flags; ``companion --help`` and
``--version`` import none of those modules, and a command imports only its own when it runs
(or shows its own help). ``tests/companion/cli/test_cli.py`` fails when NumPy, SciPy, OpenCV or the
simulator load for ``--help``, ``--version`` or ``status``. A new command is one more
:class:`Command` row (its module's ``add_*(sub)`` calls ``sub.add_parser(name, help=...)``
once, with the same help as the row).

Exit codes: :data:`companion.cli.common.EXIT_CODES` (docs/service.md, "Exit codes").
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NoReturn

from companion import __version__
from companion.cli.common import (
    EXIT_BROKEN_PIPE,
    EXIT_CODES,
    EXIT_CONFIG,
    EXIT_ERROR,
    EXIT_INTERRUPTED,
    EXIT_NOT_RUNNING,
    EXIT_OK,
    EXIT_PROBLEMS,
    EXIT_UNREACHABLE,
    EXIT_USAGE,
    json_error,
)
from companion.errors import CompanionError, ConfigError, DatasetError, UnreachableError

__all__ = [
    "COMMANDS",
    "EXIT_BROKEN_PIPE",
    "EXIT_CONFIG",
    "EXIT_ERROR",
    "EXIT_INTERRUPTED",
    "EXIT_NOT_RUNNING",
    "EXIT_OK",
    "EXIT_PROBLEMS",
    "EXIT_UNREACHABLE",
    "EXIT_USAGE",
    "Command",
    "build_parser",
    "format_status",
    "main",
]


@dataclass(frozen=True)
class Command:
    """A subcommand of ``companion``: ``register(sub)`` in ``module`` adds its parser (flags
    and handler) when the command is used; ``help`` is what ``companion --help`` shows without
    importing ``module`` (tests/companion/cli/test_cli.py checks that it is the module's own
    help)."""

    name: str
    help: str
    module: str
    register: str


# the subcommands in the order `companion --help` lists them: the board's, then the desk's
COMMANDS: tuple[Command, ...] = (
    Command(
        "run",
        "the service (camera + rangefinders -> autopilot)",
        "companion.cli.service",
        "add_run",
    ),
    Command(
        "status",
        "the running service's state (exit 3 if none)",
        "companion.cli.service",
        "add_status",
    ),
    Command("config", "print the effective configuration", "companion.cli.service", "add_config"),
    Command(
        "px4",
        "check / configure PX4 so that EKF2 fuses our estimate",
        "companion.autopilot.cli",
        "add_px4_parser",
    ),
    Command(
        "autopilot",
        "check / configure PX4 or ArduPilot (by its HEARTBEAT)",
        "companion.autopilot.cli",
        "add_parser",
    ),
    Command(
        "calibrate",
        "camera intrinsics; check the rangefinder mounts",
        "companion.cli.calibrate",
        "add_parser",
    ),
    Command(
        "eval",
        "evaluate the pipeline on a dataset or a SITL flight",
        "companion.cli.evaluate",
        "add_eval",
    ),
    Command(
        "report",
        "summarise scale evaluations over seeds",
        "companion.cli.evaluate",
        "add_report",
    ),
    Command(
        "results",
        "regenerate the tables of docs/RESULTS.md (a batch)",
        "companion.cli.results",
        "add_results",
    ),
    Command(
        "sweep",
        "a grid of config values over datasets or flights",
        "companion.cli.results",
        "add_sweep",
    ),
    Command(
        "replay",
        "re-run flight recordings through this version",
        "companion.cli.replay",
        "add_replay",
    ),
    Command(
        "compare",
        "what changed between two replays (companion replay)",
        "companion.cli.replay",
        "add_compare",
    ),
    Command(
        "dataset",
        "import real sequences into our dataset format",
        "companion.cli.dataset",
        "add_parser",
    ),
    Command("bench", "benchmarks", "companion.cli.bench", "add_bench"),
    Command("sitl", "the simulator", "companion.cli.sim", "add_sitl"),
    Command(
        "demo", "SITL autopilot + service together, with a summary", "companion.cli.sim", "add_demo"
    ),
)

DESCRIPTION = (
    "companion: metric position and drift-free roll/pitch for PX4 from a downward camera and\n"
    "laser rangefinders, on the vehicle's companion computer (`run`, under systemd: `status`),\n"
    "with the tools around it: PX4 set-up (`px4`), calibration, evaluation on datasets,\n"
    "benchmarks and a simulator."
)

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def _epilog() -> str:
    rows = "\n".join(f"  {code:>3}  {meaning}" for code, meaning in EXIT_CODES)
    return (
        f"exit codes (docs/service.md):\n{rows}\n\n"
        "--json: errors, too, are one JSON object on stdout: "
        '{"error": ..., "exit_code": ..., "kind": ...}'
    )


class UsageError(Exception):
    """A bad command line (argparse's error): exit 2, as text or, under --json, as JSON."""

    def __init__(self, parser: argparse.ArgumentParser, message: str) -> None:
        super().__init__(f"{parser.prog}: {message}")
        self.parser = parser


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors reach :func:`main` (which knows about --json) instead of
    printing and exiting on the spot."""

    def error(self, message: str) -> NoReturn:
        raise UsageError(self, message)

    def _print_message(self, message: str, file: Any = None) -> None:
        """As argparse's, but a closed stdout reaches :func:`main` (exit 141) instead of being
        ignored (which made ``--help`` exit 0 or 141 depending on the stream's buffering)."""
        if message:
            try:
                (file or sys.stderr).write(message)
            except BrokenPipeError:
                raise
            except (AttributeError, OSError):
                pass


class _CommandParser(_Parser):
    """A subcommand's parser: empty until used (parsing or its --help), then filled by its
    :class:`Command`'s register function. Every subcommand parser also takes -v/--log-level."""

    def __init__(self, *args: Any, command: Command | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.command = command
        self.module_help: str | None = None  # what the module passed to add_parser(help=...)
        self._loaded = command is None  # nested parsers (px4 check) are filled by their module
        _add_log_flags(self, argparse.SUPPRESS)  # given after the command: overrides the top's

    def load(self) -> None:
        """Import the command's module and let it add its flags (once)."""
        if self._loaded or self.command is None:
            return
        self._loaded = True
        module = importlib.import_module(self.command.module)
        getattr(module, self.command.register)(_OneParser(self))
        if self.description is None:
            self.description = self.command.help

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        self.load()
        return super().parse_known_args(args, namespace)

    def format_help(self) -> str:
        self.load()
        return super().format_help()

    def format_usage(self) -> str:
        self.load()
        return super().format_usage()


class _OneParser:
    """What a module's ``add_*(sub)`` is given: ``sub.add_parser(name, help=...)`` returns the
    command's (already registered) parser instead of making a new one."""

    SETTABLE = frozenset({"description", "epilog", "formatter_class", "usage"})

    def __init__(self, parser: _CommandParser) -> None:
        self.parser = parser

    def add_parser(self, name: str, **kwargs: Any) -> argparse.ArgumentParser:
        """The parser of command ``name`` (the one this was made for)."""
        assert self.parser.command is not None
        if name != self.parser.command.name:
            raise TypeError(
                f"{self.parser.command.module}.{self.parser.command.register} adds {name!r}, "
                f"but companion.cli.COMMANDS registers it for {self.parser.command.name!r}"
            )
        self.parser.module_help = kwargs.pop("help", None)
        unknown = set(kwargs) - self.SETTABLE
        if unknown:
            raise TypeError(f"add_parser({name!r}): {sorted(unknown)} not supported here")
        for key, value in kwargs.items():
            setattr(self.parser, key, value)
        return self.parser


def _add_log_flags(p: argparse.ArgumentParser, default: Any) -> None:
    p.add_argument(
        "-v",
        "--verbose",
        dest="log_level",
        action="store_const",
        const="DEBUG",
        default=default,
        help="log everything (the same as --log-level DEBUG)",
    )
    p.add_argument(
        "--log-level",
        dest="log_level",
        type=str.upper,
        choices=LOG_LEVELS,
        default=default,
        metavar="LEVEL",
        help=f"{', '.join(LOG_LEVELS)} (default: INFO for run, WARNING otherwise)",
    )


def build_parser(load_all: bool = False) -> argparse.ArgumentParser:
    """The argument parser of ``companion``; the commands' own flags are added when a command
    is parsed, or all at once with ``load_all`` (which imports every command module)."""
    parser = _Parser(
        prog="companion",
        description=DESCRIPTION,
        epilog=_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--version",
        action="version",
        version=f"companion {__version__}",
        help="print the version and exit",
    )
    _add_log_flags(parser, None)
    sub = parser.add_subparsers(
        dest="command",
        required=True,
        metavar="COMMAND",
        title="commands",
        help="`companion COMMAND --help` shows its flags",
        parser_class=_CommandParser,
    )
    for command in COMMANDS:
        p = sub.add_parser(command.name, help=command.help, command=command)
        if load_all:
            p.load()
    return parser


def _configure_logging(level: str | None) -> None:
    """-v / --log-level: the root logger's level and a handler on stderr. Without the flag,
    nothing changes (``run`` then logs at INFO, the other commands at WARNING)."""
    if level is None:
        return
    logging.basicConfig(level=level, format=LOG_FORMAT)
    logging.getLogger().setLevel(level)  # also when a handler was already there


def _wants_json(tokens: Sequence[str]) -> bool:
    """--json among the flags (before a ``--``): how a usage error is printed."""
    flags = tokens[: list(tokens).index("--")] if "--" in tokens else tokens
    return "--json" in flags


def _fail(message: str, code: int, kind: str, as_json: bool, **extra: Any) -> int:
    """Print an error (stderr; or JSON on stdout under --json) and return its exit code."""
    if as_json:
        print(json_error(message, code, kind, **extra), flush=True)
    else:
        print(f"companion: {kind}: {message}", file=sys.stderr)
    return code


# modules that only an extra installs (pyproject.toml): a command that needs one says which
# extra, instead of a traceback, on a board that has the runtime dependencies alone
_EXTRA_OF_MODULE = {
    "numba": "sim",
    "llvmlite": "sim",
    "skimage": "sim",
    "tomli_w": "sim",
    "matplotlib": "eval",
    "evo": "eval",
    "ray": "cluster",
}


def _run(argv: Sequence[str] | None) -> int:
    tokens = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        args = parser.parse_args(tokens)
    except UsageError as e:
        if _wants_json(tokens):
            return _fail(str(e), EXIT_USAGE, "usage", True)
        e.parser.print_usage(sys.stderr)
        print(f"{e}", file=sys.stderr)
        return EXIT_USAGE
    except SystemExit as e:  # --help, --version
        return int(e.code) if isinstance(e.code, int) else EXIT_USAGE
    _configure_logging(args.log_level)
    as_json = bool(getattr(args, "json", False))
    try:
        code: int = args.func(args)
        return code
    except ConfigError as e:
        return _fail(str(e), EXIT_USAGE, "config error", as_json)
    except DatasetError as e:  # a refused input file (the message names file, row and field)
        return _fail(str(e), EXIT_USAGE, "dataset error", as_json)
    except UnreachableError as e:
        return _fail(str(e), EXIT_UNREACHABLE, "unreachable", as_json)
    except CompanionError as e:
        return _fail(str(e), EXIT_PROBLEMS, "error", as_json)
    except KeyboardInterrupt:
        return _fail("interrupted", EXIT_INTERRUPTED, "interrupted", as_json)
    except ModuleNotFoundError as e:
        extra = _EXTRA_OF_MODULE.get((e.name or "").split(".")[0])
        if extra is None:
            raise
        message = (
            f"this command needs the {extra!r} extra ({e.name} is not installed): "
            f"pip install 'companion[{extra}]' (make venv installs every extra)"
        )
        return _fail(message, EXIT_PROBLEMS, "missing extra", as_json)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``companion`` console script; returns the exit code.

    A reader that closes stdout early (``companion config | head -1``) ends the command
    quietly with 141, the code of a program killed by SIGPIPE (what ``set -o pipefail`` sees
    from ``seq 100000 | head -1``): stdout is pointed at /dev/null so that the final flush
    raises nothing either (the recipe in Python's ``signal`` documentation)."""
    try:
        code = _run(argv)
        sys.stdout.flush()
        return code
    except BrokenPipeError:
        _stdout_to_devnull()
        return EXIT_BROKEN_PIPE


def _stdout_to_devnull() -> None:
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # stdout without a file descriptor (a test's capture)
        pass


def __getattr__(name: str) -> Any:
    """``format_status`` (the status table) from its module, loaded on first use."""
    if name == "format_status":
        from companion.cli.service import format_status

        return format_status
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""A batch task: a frozen, hashable description of one run of ``companion eval`` or
``companion replay`` (kind, the command's arguments, the input folders, the config and the
overrides laid over it), and the config file it runs with.

A task is a pure function of its spec: the same spec on the same code gives the same result
folder (the runs are seeded; docs/RESULTS.md). The spec holds no absolute output path: the
result folder is chosen by whoever runs it (``{out}`` in ``argv`` stands for it).
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

from companion.errors import BatchError, ConfigError

TaskKind = Literal["flight", "sequence", "replay", "sweep"]
OUT = "{out}"  # in argv: the task's result folder
Scalar = str | int | float | bool
Override = tuple[str, Scalar]  # ("vo.max_features", 150)


@dataclass(frozen=True, slots=True)
class Task:
    """One task. ``name``: its result folder under the batch's output folder (may hold a
    ``/``: ``real/tum_fr1_rpy``); ``argv``: the ``companion`` command line without
    ``--config`` (``{out}`` for the result folder); ``inputs``: the folders and files it reads
    (hashed by content for the cache); ``config``: a TOML config file or None (the built-in
    one, or a recording's own); ``overrides``: dotted keys laid over that config."""

    kind: TaskKind
    name: str
    argv: tuple[str, ...]
    inputs: tuple[str, ...] = ()
    config: str | None = None
    overrides: tuple[Override, ...] = ()

    def with_overrides(self, overrides: Iterable[Override], name: str) -> Task:
        """This task with more overrides (a sweep point), under another name."""
        return replace(self, kind="sweep", name=name, overrides=self.overrides + tuple(overrides))


def flight(
    name: str,
    terrain: str,
    trajectory: str,
    seed: int,
    seconds: float,
    flags: Iterable[str] = ("--methods", "all"),
    config: str | None = None,
    overrides: tuple[Override, ...] = (),
) -> Task:
    """A simulated flight through ``companion eval`` (``flags``: ``--methods all``,
    ``--attitude --spacing 0.5``, ``--dpose``, ...); ``seconds`` of flight."""
    argv: tuple[str, ...] = ("eval", "--terrain", terrain, "--trajectory", trajectory)
    argv += ("--seconds", f"{seconds:g}", "--seed", str(seed), *flags, "--no-progress")
    return Task("flight", name, (*argv, "--out", OUT), (), config, overrides)


def sim_eval(name: str, flags: Iterable[str], config: str | None = None) -> Task:
    """A simulated ``companion eval`` given by its flags alone (``--dpose --random 10000``)."""
    return Task("flight", name, ("eval", *flags, "--no-progress", "--out", OUT), (), config)


def sequence(
    name: str,
    dataset: str | Path,
    flags: Iterable[str] = ("--methods", "all"),
    config: str | None = None,
    overrides: tuple[Override, ...] = (),
) -> Task:
    """A dataset folder (a real sequence, a recorded flight) through ``companion eval``."""
    path = str(dataset)
    argv = ("eval", path, *flags, "--no-progress", "--out", OUT)
    return Task("sequence", name, argv, (path,), config, overrides)


def replay(
    name: str,
    recording: str | Path,
    config: str | None = None,
    overrides: tuple[Override, ...] = (),
) -> Task:
    """A flight recording through ``companion replay`` (``config``: an override file)."""
    path = str(recording)
    argv = ("replay", path, "--json", f"{OUT}/replay.json", "--no-progress")
    return Task("replay", name, argv, (path,), config, overrides)


# ------------------------------------------------------------------------------ overrides
def parse_value(text: str) -> Scalar:
    """A value of ``--grid key=v1,v2`` as TOML reads it (``150`` int, ``0.5`` float, ``true``
    bool), else the text itself (``magnetometer``)."""
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text
    if isinstance(value, str | int | float | bool):
        return value
    return text


def nested(overrides: Iterable[Override]) -> dict[str, Any]:
    """Dotted overrides as the nested dict ``load_config`` merges:
    ``[("vo.max_features", 150)]`` -> ``{"vo": {"max_features": 150}}``."""
    out: dict[str, Any] = {}
    for key, value in overrides:
        parts = key.split(".")
        if not all(parts):
            raise ConfigError(f"{key}: not a config key (section.key)")
        table = out
        for part in parts[:-1]:
            table = table.setdefault(part, {})
            if not isinstance(table, dict):
                raise ConfigError(f"{key}: {part} is both a value and a table")
        table[parts[-1]] = value
    return out


def to_toml(data: Mapping[str, Any]) -> str:
    """A nested dict of TOML values as TOML text: tables as ``[a.b]`` sections, lists inline
    (a list of tables as inline tables: ``rangefinders = [{id = 1, ...}]``)."""
    lines: list[str] = []
    _table(data, (), lines)
    return "\n".join(lines).strip() + "\n"


def _table(data: Mapping[str, Any], path: tuple[str, ...], lines: list[str]) -> None:
    plain = {k: v for k, v in data.items() if not isinstance(v, Mapping)}
    tables = {k: v for k, v in data.items() if isinstance(v, Mapping)}
    if path and (plain or not tables):
        lines.append(f"\n[{'.'.join(_key(p) for p in path)}]")
    lines.extend(f"{_key(k)} = {_value(v)}" for k, v in plain.items())
    for k, v in tables.items():
        _table(v, (*path, k), lines)


def _key(key: str) -> str:
    bare = key.replace("_", "").replace("-", "").isalnum()
    return key if bare else json.dumps(key)


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a TOML basic string
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + "}"
    raise BatchError(f"{v!r}: not a TOML value")

"""TOML text of plain data for the recorder's small files (no TOML writer among the
service's dependencies)."""

from __future__ import annotations

import json
import re
from typing import Any

_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v)  # shortest exact text; inf and nan are TOML's spelling too
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string (\uXXXX escapes are TOML's too)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"no TOML for {type(v).__name__}")


def _toml_key(k: str) -> str:
    return k if _BARE_KEY.match(k) else json.dumps(k)


def _toml_lines(data: dict[str, Any], prefix: tuple[str, ...] = ()) -> list[str]:
    def table_list(v: Any) -> bool:
        return isinstance(v, (list, tuple)) and bool(v) and all(isinstance(x, dict) for x in v)

    lines = [
        f"{_toml_key(k)} = {_toml_value(v)}"
        for k, v in data.items()
        if not isinstance(v, dict) and not table_list(v)
    ]
    for k, v in data.items():
        name = ".".join(_toml_key(p) for p in (*prefix, k))
        if isinstance(v, dict):
            lines += ["", f"[{name}]", *_toml_lines(v, (*prefix, k))]
        elif table_list(v):
            for item in v:
                lines += ["", f"[[{name}]]", *_toml_lines(item, (*prefix, k))]
    return lines


def toml_dumps(data: dict[str, Any]) -> str:
    """TOML text of plain data (tables, arrays of tables, scalars, lists), floats exact: the
    recorder's small files, without a TOML writer among the service's dependencies."""
    return "\n".join(_toml_lines(data)).lstrip("\n") + "\n"

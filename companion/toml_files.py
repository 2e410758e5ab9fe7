"""Reading TOML files and text safely (configs, calibrations, dataset metadata, manifests):
strict UTF-8, bounded size and nesting checked before the parser recurses, every failure an
error of the caller's kind naming the file; a config file's ``extends``; and the recursive merge
of two tables."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Any

from companion.bounded import data_nesting, read_regular_file
from companion.errors import CompanionError, ConfigError

MAX_CONFIG_BYTES = 1 << 20  # a config is a few kB; more is not a config
MAX_TOML_DEPTH = 16  # tables and arrays nested deeper than this are not a config or a dataset
# what the TOML scanner looks at: strings (their start), comments, brackets, keys' dots, = , \n
_TOML_TOKEN = re.compile(r"\"\"\"|'''|[\"'#\[\]{}=.,\n]")
_TOML_STRING_END = {
    '"""': re.compile(r'(?:[^"\\]|\\.|"(?!""))*"""', re.DOTALL),
    "'''": re.compile(r"(?:[^']|'(?!''))*'''", re.DOTALL),
    '"': re.compile(r'(?:[^"\\\n]|\\.)*"'),
    "'": re.compile(r"[^'\n]*'"),
}


def decode_utf8(raw: bytes, where: str, error: type[CompanionError] = ConfigError) -> str:
    """``raw`` as UTF-8 text (strict; a leading BOM dropped); ``error`` naming ``where`` and the
    byte offset otherwise, and for a NUL byte (no text file of ours holds one)."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(f"{where}: not UTF-8 text (byte {e.start}): {e.reason}") from None
    nul = text.find("\x00")
    if nul >= 0:
        raise error(f"{where}: a NUL byte at character {nul}: not a text file")
    return text.removeprefix("\ufeff")


def toml_nesting(text: str) -> int:
    """How deeply the TOML ``text`` nests tables and arrays (an upper bound, read without
    parsing: brackets of values, and the dots of keys and table headers, outside strings
    and comments), so that a document nested 30,000 deep is refused before the parser
    recurses into it."""
    deepest = key_dots = 0
    open_brackets: list[str] = []
    in_key, header = True, False
    pos, n = 0, len(text)
    while pos < n:
        m = _TOML_TOKEN.search(text, pos)
        if m is None:
            break
        tok, pos = m.group(), m.end()
        if tok in _TOML_STRING_END:
            end = _TOML_STRING_END[tok].match(text, pos)
            pos = end.end() if end else n  # an unterminated string: the parser says so
        elif tok == "#":
            newline = text.find("\n", pos)
            pos = n if newline < 0 else newline
        elif tok == "\n" and (header or not open_brackets):
            in_key, header, key_dots = True, False, 0
            open_brackets.clear()
        elif tok == "." and (in_key or header):
            key_dots += 1
        elif tok == "=":
            in_key, key_dots = False, 0
        elif tok in "[{":
            header = header or (in_key and not open_brackets)
            open_brackets.append(tok)
            in_key = tok == "{"
        elif tok in "]}" and open_brackets:
            open_brackets.pop()
        elif tok == ",":
            in_key = bool(open_brackets) and open_brackets[-1] == "{"
        deepest = max(deepest, len(open_brackets) + key_dots)
    return deepest


def parse_toml(
    text: str,
    where: str,
    error: type[CompanionError] = ConfigError,
    max_depth: int = MAX_TOML_DEPTH,
) -> dict[str, Any]:
    """The TOML table of ``text``; ``error`` naming ``where`` for anything else: a syntax
    error, nesting deeper than ``max_depth`` (checked before parsing), an integer too long to
    read."""
    if toml_nesting(text) > max_depth:
        raise error(f"{where}: tables or arrays nested deeper than {max_depth}: not read")
    try:
        data = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, ValueError, RecursionError) as e:
        # ValueError: an int too long to read; RecursionError: a nesting the scan missed
        raise error(f"{where}: not valid TOML: {str(e)[:200]}") from None
    if data_nesting(data) > max_depth:
        raise error(f"{where}: tables or arrays nested deeper than {max_depth}: not read")
    return data


def read_toml(path: Path) -> dict[str, Any]:
    """The TOML table in ``path``; ConfigError naming the file for anything that is not a
    readable UTF-8 TOML file (missing, a directory, a FIFO or a device, unreadable, too big,
    bad bytes, nested too deep)."""
    raw = read_regular_file(path, MAX_CONFIG_BYTES, ConfigError)
    return parse_toml(decode_utf8(raw, str(path)), str(path))


MAX_EXTENDS = 8  # config files extending one another: more than this is a mistake


def read_config_toml(path: Path, _chain: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A config file's table with what it ``extends`` laid under it: a top-level
    ``extends = "realistic.toml"`` (a path relative to the file) names a config file whose
    table this file's is merged over (:func:`merge`), recursively. ConfigError naming the file
    for a non-string, a missing base, or a chain that loops or is longer than MAX_EXTENDS."""
    data = read_toml(path)
    base = data.pop("extends", None)
    if base is None:
        return data
    if not isinstance(base, str) or not base:
        raise ConfigError(f"{path}: extends: the path of a config file, got {base!r}")
    chain = (*_chain, path.resolve())
    base_path = path.parent / base
    if base_path.resolve() in chain or len(chain) > MAX_EXTENDS:
        names = " -> ".join(str(p.name) for p in (*chain, base_path))
        raise ConfigError(f"{path}: extends: a loop or a chain over {MAX_EXTENDS}: {names}")
    try:
        under = read_config_toml(base_path, chain)
    except ConfigError as e:
        raise ConfigError(f"{path}: extends: {e}") from None
    return merge(under, data)


def merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """Recursive dict merge (tables merged, other values replaced)."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = merge(out[k], v)
        else:
            out[k] = v
    return out

"""How deeply parsed data nests, without recursion: one bound for everything we parse from
outside (TOML files, a status reply's JSON), light enough for `companion status` to import
(no NumPy)."""

from __future__ import annotations

from typing import Any


def data_nesting(value: Any) -> int:
    """How deeply ``value`` (parsed TOML or JSON: dicts and lists) nests: 0 for a scalar, 1 for
    a flat table or list. Iterative, so a hostile 30,000-deep document costs no recursion."""
    deepest = 0
    stack: list[tuple[Any, int]] = [(value, 0)]
    while stack:
        item, depth = stack.pop()
        deepest = max(deepest, depth)
        if isinstance(item, dict):
            stack.extend((v, depth + 1) for v in item.values())
        elif isinstance(item, list):
            stack.extend((v, depth + 1) for v in item)
    return deepest

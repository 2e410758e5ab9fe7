"""Secrets out of text that leaves the process (logs, warnings, MQTT, the status socket).

A camera URL may carry credentials (``rtsp://user:pass@host/stream``); a MQTT password is a
config value. Everything that prints a URL goes through :func:`redact_url`, and every warning
through :func:`redact_text` with the secrets of the running config, so that a driver's error
message that quotes the URL does not leak it either.
"""

from __future__ import annotations

import re
from collections.abc import Iterable

# scheme://userinfo@ : userinfo is everything up to the last '@' before the host part
_USERINFO = re.compile(r"(?P<scheme>[A-Za-z][A-Za-z0-9+.\-]*://)(?P<userinfo>[^/?#\s@]*)@")

MASK = "***"


def redact_url(url: str) -> str:
    """``url`` with the password of its userinfo masked: ``rtsp://user:***@host/path``
    (a user name without a password is kept; every ``scheme://...@`` in the text is masked,
    so a GStreamer pipeline with an ``rtspsrc location=...`` is covered too)."""

    def mask(m: re.Match[str]) -> str:
        user, sep, _password = m["userinfo"].partition(":")
        return f"{m['scheme']}{user}{':' + MASK if sep else ''}@"

    return _USERINFO.sub(mask, url)


def url_secrets(url: str) -> list[str]:
    """The passwords inside ``url``'s userinfo parts (to mask wherever they appear)."""
    out = []
    for m in _USERINFO.finditer(url):
        _user, sep, password = m["userinfo"].partition(":")
        if sep and password:
            out.append(password)
    return out


def redact_text(text: str, secrets: Iterable[str] = ()) -> str:
    """``text`` with URL credentials masked and every non-empty secret replaced by ``***``."""
    out = redact_url(text)
    for secret in sorted({s for s in secrets if s}, key=len, reverse=True):
        out = out.replace(secret, MASK)
    return out

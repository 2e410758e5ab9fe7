"""Secrets out of text that leaves the process (logs, warnings, MQTT, the status socket).

A camera URL may carry credentials: in a URL's userinfo (``rtsp://user:pass@host/stream``,
where the password may itself hold an ``@``: the userinfo runs to the last ``@`` before the
host) and, in a GStreamer pipeline, in an element's credential properties (``user-id=``,
``user-pw=``, ``proxy-id=``, ``proxy-pw=`` of souphttpsrc and rtspsrc, ``passphrase=`` of
srtsrc, and any property named like a password, a secret, a token or an access key). A MQTT
password is a config value. Everything that prints a URL goes through :func:`redact_url`, and
every warning through :func:`redact_text` with the secrets of the running config, so that a
driver's error message that quotes the URL or the password does not leak it either.

A secret is searched for in free text only when it has at least MIN_SECRET_CHARS characters:
a one-letter password replaced everywhere would mangle every warning (and say which letter it
is); a short one is still masked where it stands (in a URL, in a property).
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from urllib.parse import unquote

# scheme://userinfo@ : the userinfo runs to the last '@' before the path, query or fragment
# (a password with an unescaped '@' is taken whole, not cut at its first '@')
_USERINFO = re.compile(r"(?P<scheme>[A-Za-z][A-Za-z0-9+.\-]*://)(?P<userinfo>[^/?#\s]*)@")

# GStreamer's credential properties: who (masked, not searched for elsewhere) ...
_GST_IDENTITY = r"(?:user|proxy)-id|user(?:name)?|login"
# ... and the secrets (masked, and searched for in free text)
_GST_SECRET = (
    r"(?:user|proxy)-pw"
    r"|[\w-]*(?:passw(?:or)?d|passphrase|secret|token|credentials?)[\w-]*"
    r"|(?:[\w]+-)*(?:access|api|auth|private|secret)-key(?:-id)?"
)
# name=value in gst-launch syntax; the value quoted ("a b", 'a b') or up to a space, a '!'
# (the next element) or a quote (the end of a repr()'d string around the pipeline)
_GST_PROPERTY = re.compile(
    rf"(?<![\w-])(?P<name>{_GST_SECRET}|{_GST_IDENTITY})\s*=\s*"
    r"""(?P<value>"(?:[^"\\]|\\.)*"|'[^']*'|[^\s!'"]+)""",
    re.IGNORECASE,
)
_GST_SECRET_NAME = re.compile(rf"(?:{_GST_SECRET})\Z", re.IGNORECASE)

MASK = "***"
MIN_SECRET_CHARS = 4  # a shorter secret is masked where it stands, not searched for in text


def _unquoted(value: str) -> str:
    """A gst-launch property value without its quotes (``"a b"`` -> ``a b``)."""
    if len(value) >= 2 and value[0] == value[-1] and value[0] in "\"'":
        return value[1:-1].replace('\\"', '"')
    return value


def _at_fragments(password: str) -> list[str]:
    """What a URL parser that ends the userinfo at the first '@' shows of a password with
    '@' (libsoup: the "host" ``ss@host`` of ``user:p@ss@host``): its pieces between '@'
    and each tail after one."""
    pieces = password.split("@")
    return [*pieces, *("@".join(pieces[k:]) for k in range(1, len(pieces)))]


def redact_url(url: str) -> str:
    """``url`` with its credentials masked: the password of every ``scheme://user:pass@``
    (``rtsp://user:***@host/path``; a user name without a password is kept) and the value of
    every GStreamer credential property (``user-pw=***``), so that a pipeline is covered."""

    def mask_userinfo(m: re.Match[str]) -> str:
        user, sep, _password = m["userinfo"].partition(":")
        return f"{m['scheme']}{user}{':' + MASK if sep else ''}@"

    def mask_property(m: re.Match[str]) -> str:
        return f"{m['name']}={MASK}"

    return _GST_PROPERTY.sub(mask_property, _USERINFO.sub(mask_userinfo, url))


def url_secrets(url: str) -> list[str]:
    """The passwords inside ``url`` (a userinfo's password as written, percent-decoded and
    the pieces of it around an '@', a GStreamer secret property's value as written and
    unquoted), to mask wherever they appear."""
    out: list[str] = []
    for m in _USERINFO.finditer(url):
        _user, sep, password = m["userinfo"].partition(":")
        if sep and password:
            out += [password, unquote(password), *_at_fragments(password)]
    for m in _GST_PROPERTY.finditer(url):
        if _GST_SECRET_NAME.match(m["name"]):
            out += [m["value"], _unquoted(m["value"])]
    return list(dict.fromkeys(s for s in out if s))


def redact_text(text: str, secrets: Iterable[str] = ()) -> str:
    """``text`` with URL and GStreamer credentials masked, and every secret of at least
    MIN_SECRET_CHARS characters replaced by ``***`` wherever it appears."""
    out = redact_url(text)
    searched = {s for s in secrets if len(s) >= MIN_SECRET_CHARS}
    for secret in sorted(searched, key=len, reverse=True):
        out = out.replace(secret, MASK)
    return out

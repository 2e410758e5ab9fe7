"""Who may read the live page (companion/service/web.py), request by request.

Rules (docs/security.md's for a listener; docs/service.md, "The live page"):
- with ``web.token`` set, every request carries it, as ``?token=``, the ``X-Companion-Token``
  header or ``Authorization: Bearer TOKEN``, compared in constant time (``hmac.compare_digest``);
- without a token (the config allows that on a loopback host only) the request's Host must be
  a loopback name or address: a page of another site that a DNS rebinding points at
  127.0.0.1 names its own host, and is refused;
- a WebSocket whose Origin is not the page's own (another site in the operator's browser) is
  refused, token or not;
- the page's headers keep its token in its own tab: no referrer, no caching, no framing, and a
  content policy that lets it reach its own server only.
"""

from __future__ import annotations

import hmac
from collections.abc import Mapping
from urllib.parse import urlsplit

from companion.service_options import is_loopback

PAGE_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; "
        "img-src 'self' blob: data:; connect-src 'self'; base-uri 'none'; form-action 'none'; "
        "frame-ancestors 'none'"
    ),
    "Referrer-Policy": "no-referrer",  # the token in the page's URL goes nowhere
    "X-Content-Type-Options": "nosniff",
    "Cache-Control": "no-store",
}


def given_token(query: Mapping[str, str], headers: Mapping[str, str]) -> str:
    """The token a request carries (empty: none)."""
    auth = headers.get("Authorization", "")
    return (
        query.get("token")
        or headers.get("X-Companion-Token")
        or (auth[7:] if auth.startswith("Bearer ") else "")
    )


def authorised(token: str, host: str, query: Mapping[str, str], headers: Mapping[str, str]) -> bool:
    """Whether a request may read the page: it carries ``token`` (when one is configured),
    else it names a loopback ``host`` (its Host header, ``name[:port]``)."""
    if not token:
        return is_loopback(urlsplit(f"//{host}").hostname or "")
    return hmac.compare_digest(given_token(query, headers).encode(), token.encode())


def same_origin(origin: str | None, host: str) -> bool:
    """Whether a WebSocket's Origin header (None: not a browser's) is the page's own host."""
    return origin is None or urlsplit(origin).netloc == host

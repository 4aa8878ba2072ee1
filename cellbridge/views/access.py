"""Who may talk to a view's server: the ``Host`` and ``Origin`` checks of ``web`` and ``foxglove``.

Both servers listen on loopback (``web`` elsewhere only with a token), but a loopback
port is not out of a browser's reach: any page the operator opens may try it. Two
attacks, two checks (pure functions: a request's headers in, a yes or no out):

- **Cross-site WebSocket hijacking.** A page of another site opens a WebSocket to the
  view and reads the skin: browsers send such a request with that site's ``Origin``.
  :func:`origin_allowed` admits an upgrade only from the view's own page (an ``Origin``
  whose host and port are the request's ``Host``), from an origin the operator listed,
  or without ``Origin`` at all: programs other than browsers (the Foxglove desktop
  app, ``websockets`` clients) send none, and a browser always sends one.
- **DNS rebinding.** A site's own name is made to resolve to 127.0.0.1: its page is
  then same-origin with the view. The browser still names that site in ``Host``:
  :func:`host_allowed` admits only names the view is known by (``localhost``, the bind
  host, names given with ``--allow-host``) and IP address literals (a page loaded from
  an address cannot be rebound: its origin is that address).
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable
from urllib.parse import urlsplit

LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback"})
FOXGLOVE_WEB = "https://app.foxglove.dev"  #: Foxglove's web app: allowed by ``cellbridge foxglove``


def split_host(host: str) -> tuple[str, int | None]:
    """``Host`` header (``name``, ``name:port``, ``[v6]:port``) as (lower-case name, port or None).
    The name is '' when the header is not of that form."""
    host = host.strip().lower()
    if host.startswith("["):
        name, sep, rest = host[1:].partition("]")
        if not sep:
            return "", None
        port = rest[1:] if rest.startswith(":") else None
        if rest and port is None:
            return "", None
    else:
        name, sep, port = host.rpartition(":") if host.count(":") == 1 else (host, "", None)
        if not sep:
            name, port = host, None
    if port is not None and not (port.isdigit() and 0 < int(port) < 65536):
        return "", None
    return name.rstrip("."), int(port) if port is not None else None


def is_ip_literal(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
        return True
    except ValueError:
        return False


def host_allowed(host: str | None, names: Iterable[str] = ()) -> bool:
    """Whether a request's ``Host`` header names this server as the view knows itself:
    a loopback name, an IP address literal, or one of ``names`` (the bind host and the
    operator's ``--allow-host``), case-insensitive. A request without ``Host`` (HTTP/1.0,
    a program) is allowed: a browser always sends one."""
    if host is None:
        return True
    name, _ = split_host(host)
    if not name:
        return False
    if name in LOOPBACK_NAMES or is_ip_literal(name):
        return True
    return name in {n.strip().lower().rstrip(".") for n in names}


def origin_allowed(origin: str | None, host: str | None, allowed: Iterable[str] = ()) -> bool:
    """Whether a WebSocket upgrade with this ``Origin`` may proceed: no ``Origin`` (not a
    browser); the view's own page (scheme http or https, host and port those of the
    ``Host`` header); or an origin in ``allowed`` (``https://app.foxglove.dev``),
    compared as scheme://host[:port], case-insensitive. ``null`` (a sandboxed frame, a
    file) is refused."""
    if origin is None:
        return True
    origin = origin.strip().lower().rstrip("/")
    if origin in {a.strip().lower().rstrip("/") for a in allowed}:
        return True
    try:
        parts = urlsplit(origin)
        oport = parts.port
    except ValueError:
        return False
    if parts.scheme not in ("http", "https") or not parts.hostname or host is None:
        return False
    name, port = split_host(host)
    default = 443 if parts.scheme == "https" else 80
    return bool(name) and parts.hostname.rstrip(".") == name and (oport or default) == (port or default)

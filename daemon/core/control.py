"""Control requests: msgpack maps in, validated :class:`Request` out, or an error that says what was wrong.

Sans-I/O: the service's ROUTER socket hands each request body here and sends back
whatever comes out. A malformed or unknown request is answered with
``{"v": 1, "ok": false, "error": "..."}`` naming the key and value at fault; nothing a
client sends can stop the daemon.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import msgpack
from cellbridge.daemon.core.wire import OPS, mode_value

from cellbridge.errors import CellbridgeError

VERSION = 1
MAX_BRIDGE = 0xFFFE  # 0xFFFF is the broadcast address
COMMANDS = {
    "status": "health of links, bridges and publisher, as on the health topic",
    "topology": "bridges, parents, path costs, gateways and the layout",
    "ping": "without bridge: is the daemon alive; with bridge: round trip to that bridge",
    "tare": "re-take the baseline of some bridges' elements (bridges: [ids]) or all",
    "set": "param (" + ", ".join(OPS) + ") to value on bridge (an id) or all bridges",
}


#: Largest ``id`` echoed back (a string or bytes); a number is always fine.
MAX_ID_BYTES = 64


class RequestError(CellbridgeError, ValueError):
    pass


def _request_id(rid: Any) -> Any:
    """The request's ``id`` if it is small: it comes back in the reply, so a client must
    not be able to make the daemon build (and send) a reply as large as its request."""
    if rid is None or isinstance(rid, (bool, int, float)):
        return rid
    if isinstance(rid, (str, bytes)) and len(rid.encode() if isinstance(rid, str) else rid) <= MAX_ID_BYTES:
        return rid
    kind = type(rid).__name__
    size = f" of {len(rid)} characters" if isinstance(rid, (str, bytes)) else ""
    raise RequestError(f"id must be a number or a string of at most {MAX_ID_BYTES} bytes, got a {kind}{size}")


def too_large(size: int, limit: int) -> dict[str, Any]:
    """The reply to a request over ``control.max_request_bytes`` (not parsed: its id is unknown)."""
    return error(f"request of {size} bytes exceeds control.max_request_bytes ({limit})")


@dataclass(frozen=True)
class Request:
    cmd: str
    bridge: int | None = None  # None: all (set) / the daemon itself (ping)
    bridges: tuple[int, ...] | None = None  # tare
    op: int | None = None
    value: int | None = None
    timeout: float | None = None
    id: Any = None  # echoed back, for clients that pipeline requests over DEALER


def _bridge_id(v: Any, key: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= MAX_BRIDGE:
        raise RequestError(f"{key} must be a bridge id in 0..{MAX_BRIDGE}, got {v!r}")
    return v


def _value(param: str, v: Any) -> int:
    if param == "mode":
        try:
            return mode_value(v)
        except ValueError as exc:
            raise RequestError(str(exc)) from None
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise RequestError(f"value for {param} must be an integer >= 0, got {v!r}")
    if param in ("rate", "gate", "oversampling") and v < 1:
        raise RequestError(f"value for {param} must be >= 1, got {v!r}")
    return v


_ALLOWED = {
    "status": set(), "topology": set(), "ping": {"bridge", "timeout"}, "tare": {"bridges"},
    "set": {"param", "value", "bridge", "timeout"},
}


def parse_request(body: bytes) -> Request:
    try:
        obj = msgpack.unpackb(body, raw=False, strict_map_key=False)
    except Exception:  # msgpack raises several unrelated types on bad input
        raise RequestError("request is not valid msgpack") from None
    if not isinstance(obj, dict):
        raise RequestError(f"request must be a msgpack map, got {type(obj).__name__}")
    v = obj.get("v", VERSION)
    if v != VERSION:
        raise RequestError(f"unsupported request version v={v!r} (this daemon speaks v={VERSION})")
    cmd = obj.get("cmd")
    if cmd not in COMMANDS:
        raise RequestError(f"unknown cmd {cmd!r} (known: {', '.join(COMMANDS)})")
    extra = set(obj) - _ALLOWED[cmd] - {"v", "cmd", "id"}
    if extra:
        raise RequestError(f"{cmd}: unknown keys {sorted(map(str, extra))} (allowed: {sorted(_ALLOWED[cmd])})")
    timeout = obj.get("timeout")
    if timeout is not None and (isinstance(timeout, bool) or not isinstance(timeout, (int, float))
                                or not 0 < timeout <= 60):
        raise RequestError(f"timeout must be seconds in (0, 60], got {timeout!r}")
    rid = _request_id(obj.get("id"))
    if cmd == "ping":
        b = obj.get("bridge")
        return Request(cmd, bridge=None if b is None else _bridge_id(b, "bridge"), timeout=timeout, id=rid,
                       op=None)
    if cmd == "tare":
        bs = obj.get("bridges")
        if bs is None or bs == "all":
            return Request(cmd, id=rid)
        if not isinstance(bs, list):
            raise RequestError(f"bridges must be a list of bridge ids or 'all', got {bs!r}")
        return Request(cmd, bridges=tuple(_bridge_id(b, "bridges[]") for b in bs), id=rid)
    if cmd == "set":
        param = obj.get("param")
        if param not in OPS:
            raise RequestError(f"param must be one of {', '.join(OPS)}, got {param!r}")
        if "value" not in obj:
            raise RequestError(f"set {param}: value missing")
        b = obj.get("bridge", "all")
        bridge = None if b == "all" else _bridge_id(b, "bridge")
        return Request(cmd, bridge=bridge, op=int(OPS[param]), value=_value(param, obj["value"]),
                       timeout=timeout, id=rid)
    return Request(cmd, id=rid)


def reply(ok: bool, rid: Any = None, **fields: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"v": VERSION, "ok": ok, **fields}
    if rid is not None:
        out["id"] = rid
    return out


def error(message: str, rid: Any = None) -> dict[str, Any]:
    return reply(False, rid, error=message)

"""The daemon's msgpack payloads as JSON messages an MCAP viewer reads, and back, losslessly.

Why JSON (with JSON Schema) and not protobuf: the payloads are open maps whose fields
are only ever *added* within a schema version (docs/zmq-api.md); JSON keeps every field a
newer daemon sends, even one this recorder's schemas do not name yet, where protobuf
would drop it. Foxglove reads ``json`` channels with ``jsonschema`` schemas directly.

Two things msgpack carries that JSON does not, and how they are kept:

- **non-finite floats** (NaN marks an invalid force, an untaken baseline...) are written
  as the strings ``"NaN"``, ``"Infinity"`` and ``"-Infinity"`` (strict JSON, so every JSON
  reader takes them; a plot shows a gap there) and turned back into floats on replay. A
  string payload value spelled exactly like one of them would come back as a float; no
  field of the API is such a string.
- **bytes** (the ``serial`` topic's ``data``) are base64, the JSON Schema
  ``contentEncoding`` Foxglove understands.

So :func:`decode` (:func:`encode` (p)) == p for every payload the daemon publishes, and
a replay republishes the very payloads that were recorded.

A recording is input like any other: a damaged or hostile file may hold anything in a
message. :func:`decode` gives a map or raises :class:`PayloadError` (never another
exception), and it refuses, before parsing, a message whose decoded form could take more
memory than a reader should give one message: over :data:`MAX_MESSAGE_BYTES`, or with
more than :data:`MAX_MESSAGE_VALUES` JSON values (a few bytes of ``{},`` become a Python
dict of ~70 bytes, so the count, not the size, bounds the memory). The recorder applies
the same bounds (:func:`check_size`) to what it writes, so every recording it makes reads
back.
"""

from __future__ import annotations

import base64
import json
import math
from typing import Any

import msgpack
import numpy as np

from cellbridge.daemon.shell.publisher import pack

#: Largest message (JSON bytes) a recording holds: a health or topology message of a skin of
#: ~10 000 bridges is a few MB.
MAX_MESSAGE_BYTES = 8 << 20
#: Most JSON values in one message (separators and brackets counted): at most ~70 bytes each
#: once decoded, so one message takes at most ~70 MB. A 16x16 element message has ~5 000.
MAX_MESSAGE_VALUES = 1_000_000


class PayloadError(ValueError):
    """A message that is not a payload of the daemon's API as recorded (not JSON, not a map,
    too large): the reader skips it and counts it; the recorder does not write it."""


NONFINITE = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}
#: Topics whose payloads hold no free text: their non-finite floats are found by a
#: pattern on the encoded text (fast) instead of a walk over every value.
COLUMNAR = frozenset({"element", "raw", "contact"})
# json.dumps writes a non-finite float as a bare token right after "[", "," or ":" (compact
# separators); plain byte replacements quote them and unquote them again (a regular
# expression costs ten times as much on a 16x16 element message).
_TOKENS = [(p + t, p + b'"' + t + b'"') for t in (b"-Infinity", b"Infinity", b"NaN") for p in (b"[", b",", b":")]


def _default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (bytes, bytearray, memoryview)):
        return base64.b64encode(bytes(obj)).decode("ascii")
    raise TypeError(f"cannot encode {type(obj).__name__}")


def _finite(obj: Any) -> Any:
    """A copy with every non-finite float replaced by its string (slow path: walks it all)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else ("NaN" if obj != obj else ("Infinity" if obj > 0 else "-Infinity"))
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    return obj


def encode(topic: str, payload: dict[str, Any]) -> bytes:
    """One payload as strict JSON (UTF-8)."""
    if topic in COLUMNAR:
        text = json.dumps(payload, separators=(",", ":"), default=_default, allow_nan=True).encode()
        if b"N" in text or b"I" in text:  # NaN or Infinity somewhere (or a capital in a name)
            for bare, quoted in _TOKENS:
                text = text.replace(bare, quoted)
        return text
    return json.dumps(_finite(payload), separators=(",", ":"), default=_default, allow_nan=False).encode()


def _restore(root: dict[str, Any] | list[Any]) -> None:
    """Non-finite floats back from their strings, in place, without recursion (a damaged file
    may nest as deep as the JSON parser goes; a copy would double the memory)."""
    stack: list[dict[str, Any] | list[Any]] = [root]
    while stack:
        node = stack.pop()
        items = node.items() if isinstance(node, dict) else enumerate(node)
        for k, v in items:
            if v.__class__ is str:
                if v in NONFINITE:
                    node[k] = NONFINITE[v]  # type: ignore[index]  # a key of this dict or an index of this list
            elif v.__class__ is dict or v.__class__ is list:
                stack.append(v)


def json_values(data: bytes) -> int:
    """An upper bound of the values :func:`json.loads` makes of ``data`` (counted in C: fast)."""
    return data.count(b",") + data.count(b":") + data.count(b"[") + data.count(b"{") + 1


def check_size(data: bytes) -> None:
    """PayloadError if the JSON message ``data`` is over the bounds every reader applies."""
    if len(data) > MAX_MESSAGE_BYTES:
        raise PayloadError(f"{len(data)} bytes, more than the {MAX_MESSAGE_BYTES} a message may have")
    n = json_values(data)
    if n > MAX_MESSAGE_VALUES:
        raise PayloadError(f"up to {n} JSON values, more than the {MAX_MESSAGE_VALUES} a message may have")


def decode(topic: str, data: bytes) -> dict[str, Any]:
    """The payload :func:`encode` was given (as msgpack would give it back: lists, floats).

    PayloadError for anything else: over the size bounds (checked before parsing), not
    JSON, nested deeper than the parser goes, not a map, a ``serial`` message whose
    ``data`` is not base64."""
    check_size(data)
    try:
        payload = json.loads(data)
    except RecursionError:
        raise PayloadError("JSON nested too deep") from None
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, an integer of too many digits
        raise PayloadError(f"not JSON: {exc}") from None
    if payload.__class__ is not dict:
        raise PayloadError(f"a JSON {type(payload).__name__}, not a map")
    if b'NaN"' in data or b'Infinity"' in data:
        if topic in ("element", "raw"):  # columns: only top-level lists hold numbers
            for k, v in payload.items():
                if v.__class__ is list and not any(x.__class__ in (list, dict) for x in v):
                    if any(x.__class__ is str for x in v):
                        payload[k] = [NONFINITE.get(x, x) if x.__class__ is str else x for x in v]
                elif v.__class__ is str:
                    payload[k] = NONFINITE.get(v, v)
                elif v.__class__ in (list, dict):
                    _restore(v)
        else:
            _restore(payload)
    if topic == "serial" and isinstance(payload.get("data"), str):
        try:
            payload["data"] = base64.b64decode(payload["data"], validate=True)
        except ValueError:  # binascii.Error
            raise PayloadError("serial data is not base64") from None
    return payload


def to_msgpack_checked(payload: dict[str, Any]) -> bytes:
    """:func:`to_msgpack`, PayloadError for what msgpack cannot hold (an integer over 64 bits,
    nesting past its limit): a decoded message of a damaged file may be either."""
    try:
        return pack(payload)
    except (ValueError, OverflowError, TypeError, RecursionError) as exc:
        raise PayloadError(f"cannot be sent as msgpack: {exc}") from None


def to_msgpack(payload: dict[str, Any]) -> bytes:
    """Packed by the daemon's own packer (docs/zmq-api.md): what a replay sends."""
    return pack(payload)


def from_msgpack(data: bytes) -> dict[str, Any]:
    """A payload as received from the daemon; ValueError if it is not a msgpack map."""
    try:
        payload = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except (msgpack.ExtraData, msgpack.FormatError, msgpack.StackError, ValueError) as exc:
        raise ValueError(f"payload is not msgpack: {exc}") from None
    if not isinstance(payload, dict):
        raise ValueError(f"payload is a msgpack {type(payload).__name__}, not a map")
    return payload

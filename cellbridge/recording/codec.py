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
"""

from __future__ import annotations

import base64
import json
import math
from typing import Any

import msgpack
import numpy as np

from cellbridge.daemon.publisher import pack

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


def _restore(obj: Any) -> Any:
    if isinstance(obj, str):
        return NONFINITE.get(obj, obj)
    if isinstance(obj, dict):
        return {k: _restore(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_restore(v) for v in obj]
    return obj


def decode(topic: str, data: bytes) -> dict[str, Any]:
    """The payload :func:`encode` was given (as msgpack would give it back: lists, floats)."""
    payload = json.loads(data)
    if b'NaN"' in data or b'Infinity"' in data:
        if topic in ("element", "raw"):  # columns: only top-level lists hold numbers
            for k, v in payload.items():
                if v.__class__ is list and not any(x.__class__ in (list, dict) for x in v):
                    if any(x.__class__ is str for x in v):
                        payload[k] = [NONFINITE.get(x, x) if x.__class__ is str else x for x in v]
                else:
                    payload[k] = _restore(v)
        else:
            payload = _restore(payload)
    if topic == "serial" and isinstance(payload.get("data"), str):
        payload["data"] = base64.b64decode(payload["data"])
    return payload


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

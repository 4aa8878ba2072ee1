"""The test vectors of docs/protocol.md §9 and §9a, regenerated from what each one states.

Run ``.venv/bin/python tests/support/protocol_doc_vectors.py`` to rewrite the vectors in the
document after a change of the encoding (``--check``: only say whether they are current,
exit status 1 when not). What each vector's source of truth is:

- ``vector`` (§9, today's version): the ``frame`` line, the JSON ``cellbridge decode``
  prints; ``wire`` and ``serial`` are what ``encode`` and ``encode_stream`` write for it.
  A new vector is added to the document with its ``frame`` line alone.
- ``vector-v1``, ``vector-v2``, ``vector-v3`` (§9a, older versions): the ``wire`` bytes an
  old sender wrote; ``frame`` is what ``decode`` reads from them, ``serial`` their
  serial-line form and ``encoded`` what ``encode`` writes for that frame today.
- ``vector-crc`` and ``vector-datagram`` are left as written.

``tests/test_protocol_vectors.py`` checks that the document is current.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Any

from cellbridge.protocol import (
    Beacon,
    BridgeStatus,
    Bundle,
    Command,
    CommandReply,
    Data,
    Fragment,
    Frame,
    FrameType,
    Hello,
    LinkAck,
    MeshTime,
    Mode,
    Neighbour,
    Op,
    Readout,
    ReadoutSame,
    ReadoutSample,
    Sample,
    Status,
    decode,
    encode,
    encode_stream,
)
from cobs import cobs

from cellbridge.decode import frame_to_json

SPEC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"
BLOCK = re.compile(r"```(vector(?:-crc|-datagram|-v1|-v2|-v3)?)\n(.*?)```", re.S)
OLD_KINDS = ("vector-v1", "vector-v2", "vector-v3")


def message_from_json(kind: str, p: dict[str, Any]) -> Any:
    """The message of type ``kind`` whose ``cellbridge decode`` JSON is ``p``."""
    if "tag" in p:  # a fragment: its slice is shown as hex
        return Fragment(FrameType(p["frame_type"]), p["tag"], p["offset"], p["total"], bytes.fromhex(p["data"]),
                        p["version"])
    if kind == "DATA":
        return Data(Mode(p["mode"]), tuple(Sample(*s) for s in p["samples"]), p["oversampling"], p["rate"],
                    p["period"])
    if kind == "BEACON":
        return Beacon(p["parent"], p["path_etx"], p["hops"], None if p["time"] is None else MeshTime(**p["time"]))
    if kind == "HELLO":
        return Hello(**p)
    if kind == "STATUS":
        return BridgeStatus(**{**p, "neighbours": tuple(Neighbour(**n) for n in p["neighbours"])})
    if kind == "CMD":
        return Command(p["token"], Op(p["op"]), p["value"])
    if kind == "CMD_REPLY":
        return CommandReply(p["token"], Op(p["op"]), Status(p["status"]), p["value"])
    if kind == "LINK_ACK":
        return LinkAck(**p)
    if kind == "BUNDLE":
        return Bundle(tuple(frame_from_json(f) for f in p["frames"]))
    if kind == "READOUT":
        return Readout(p["index"], p["rate"], Mode(p["mode"]), p["oversampling"],
                       tuple(ReadoutSample(*s) for s in p["samples"]), tuple(p["unchanged"]), tuple(p["missing"]),
                       p["span_us"], p["part"], p["parts"], p.get("root", 0), p.get("age_us", 0), p.get("ref_step", 0))
    if kind == "READOUT_SAME":
        return ReadoutSame(**p)
    raise ValueError(f"no frame type {kind!r}")


def frame_from_json(d: dict[str, Any]) -> Frame:
    """The frame ``cellbridge decode`` prints as ``d`` (the inverse of :func:`frame_to_json`)."""
    return Frame(d["src"], d["dst"], d["origin"], d["seq"], message_from_json(d["type"], d["payload"]), d["hops"],
                 d["cost"], d["flags"])


def _hex(b: bytes) -> str:
    return b.hex(" ")


def _fields(body: str) -> dict[str, str]:
    return {k.strip(): v.strip() for k, v in (line.split(":", 1) for line in body.strip().splitlines())}


def _block(kind: str, fields: dict[str, str]) -> str:
    width = max(len(k) for k in fields) + 2
    lines = "".join(f"{k + ':':<{width}}{v}\n" for k, v in fields.items())
    return f"```{kind}\n{lines}```"


def regenerate_block(kind: str, body: str) -> str:
    """One vector block as it must read (see the module's docstring)."""
    fields = _fields(body)
    if kind == "vector":
        frame = frame_from_json(json.loads(fields["frame"]))
        fields = {"frame": json.dumps(frame_to_json(frame)), "wire": _hex(encode(frame)),
                  "serial": _hex(encode_stream(frame))}
    elif kind in OLD_KINDS:
        wire = bytes.fromhex(fields["wire"])
        assert wire[0] == int(kind[-1]), f"a {kind} block holds bytes of version {wire[0]}"
        frame = decode(wire)
        fields = {"frame": json.dumps(frame_to_json(frame)), "wire": _hex(wire),
                  "serial": _hex(b"\x00" + cobs.encode(wire) + b"\x00"), "encoded": _hex(encode(frame))}
    else:
        return f"```{kind}\n{body}```"
    return _block(kind, fields)


def regenerate(text: str) -> str:
    """``text`` with every vector block regenerated."""
    return BLOCK.sub(lambda m: regenerate_block(m.group(1), m.group(2)), text)


def main(argv: list[str]) -> int:
    text = SPEC.read_text()
    new = regenerate(text)
    if "--check" in argv:
        print("current" if new == text else f"{SPEC} has vectors to regenerate")
        return 0 if new == text else 1
    if new != text:
        SPEC.write_text(new)
        print(f"rewrote the vectors of {SPEC}")
    else:
        print("vectors already current")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

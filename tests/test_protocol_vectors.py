"""The test vectors of docs/protocol.md, read from the document itself."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from cellbridge.protocol import Reassembler, StreamDecoder, crc16, decode, encode, encode_stream
from cellbridge.decode import frame_to_json

SPEC = Path(__file__).resolve().parent.parent / "docs" / "protocol.md"
BLOCK = re.compile(r"```(vector(?:-crc|-datagram)?)\n(.*?)```", re.S)


def _blocks(kind: str) -> list[dict[str, str]]:
    out = []
    for k, body in BLOCK.findall(SPEC.read_text()):
        if k == kind:
            fields = dict(line.split(":", 1) for line in body.strip().splitlines())
            out.append({key.strip(): value.strip() for key, value in fields.items()})
    return out


VECTORS = _blocks("vector")


def test_every_frame_type_has_a_vector() -> None:
    types = {json.loads(v["frame"])["type"] for v in VECTORS}
    assert types == {"DATA", "BEACON", "HELLO", "STATUS", "CMD", "CMD_REPLY", "LINK_ACK", "BUNDLE"}
    assert any(json.loads(v["frame"])["flags"] for v in VECTORS)
    assert any("tag" in json.loads(v["frame"])["payload"] for v in VECTORS)  # fragments


@pytest.mark.parametrize("vector", VECTORS, ids=lambda v: json.loads(v["frame"])["type"])
def test_vector(vector: dict[str, str]) -> None:
    wire, serial = bytes.fromhex(vector["wire"]), bytes.fromhex(vector["serial"])
    frame = decode(wire)
    assert frame_to_json(frame) == json.loads(vector["frame"])
    assert encode(frame) == wire
    assert encode_stream(frame) == serial
    assert StreamDecoder().feed(serial) == [frame]


def test_crc_vector() -> None:
    (v,) = _blocks("vector-crc")
    assert crc16(bytes.fromhex(v["input"])).to_bytes(2, "big") == bytes.fromhex(v["crc"])


def test_fragment_vectors_reassemble_to_the_datagram_vector() -> None:
    (datagram,) = _blocks("vector-datagram")
    r = Reassembler()
    fragments = [decode(bytes.fromhex(v["wire"])) for v in VECTORS if "tag" in json.loads(v["frame"])["payload"]]
    assert len(fragments) >= 2
    out = [f for f in (r.receive(x, 0.0) for x in fragments) if f is not None]
    assert [frame_to_json(f) for f in out] == [json.loads(datagram["frame"])]

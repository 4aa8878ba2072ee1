"""The test vectors of docs/protocol.md, read from the document itself."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from cellbridge.protocol import (
    VERSION,
    Frame,
    Reassembler,
    SampleFlags,
    StreamDecoder,
    crc16,
    decode,
    encode,
    encode_stream,
)
from cellbridge.decode import frame_to_json

SPEC = Path(__file__).resolve().parent.parent / "docs" / "protocol.md"
BLOCK = re.compile(r"```(vector(?:-crc|-datagram|-v1)?)\n(.*?)```", re.S)


def _blocks(kind: str) -> list[dict[str, str]]:
    out = []
    for k, body in BLOCK.findall(SPEC.read_text()):
        if k == kind:
            fields = dict(line.split(":", 1) for line in body.strip().splitlines())
            out.append({key.strip(): value.strip() for key, value in fields.items()})
    return out


def _json(vector: dict[str, str]) -> dict[str, Any]:
    """The frame a vector shows, as ``cellbridge decode --json`` prints it."""
    return json.loads(vector["frame"])


def _read(vector: dict[str, str], version: int) -> tuple[Frame, bytes, bytes]:
    """(frame, wire, serial) of a vector, after the checks every vector passes: its wire
    bytes carry ``version``, decode to the frame shown, and its serial bytes to that frame."""
    wire, serial = bytes.fromhex(vector["wire"]), bytes.fromhex(vector["serial"])
    assert wire[0] == version
    frame = decode(wire)
    assert frame_to_json(frame) == _json(vector)
    assert StreamDecoder().feed(serial) == [frame]
    return frame, wire, serial


VECTORS = _blocks("vector")
V1_VECTORS = _blocks("vector-v1")
NO_MESH_TIME = int(SampleFlags.NO_MESH_TIME)


def test_every_frame_type_has_a_vector() -> None:
    frames = [_json(v) for v in VECTORS]
    types = {f["type"] for f in frames}
    assert types == {"DATA", "BEACON", "HELLO", "STATUS", "CMD", "CMD_REPLY", "LINK_ACK", "BUNDLE"}
    assert any(f["flags"] for f in frames)
    assert any("tag" in f["payload"] for f in frames)  # fragments
    # version 2's fields, each shown with a value other than its default
    payloads = [f["payload"] for f in frames]
    data = [p for f, p in zip(frames, payloads) if f["type"] == "DATA" and "samples" in p]
    assert any(p["rate"] and all(s[5] and not s[4] & NO_MESH_TIME for s in p["samples"]) for p in data)
    assert any(p["rate"] and all(s[4] & NO_MESH_TIME for s in p["samples"]) for p in data)
    assert any(f["type"] == "BEACON" and f["payload"]["time"] is not None for f in frames)
    assert any(f["type"] == "BEACON" and f["payload"]["time"] is None for f in frames)
    assert any(f["type"] == "HELLO" and f["payload"]["boots"] for f in frames)


@pytest.mark.parametrize("vector", VECTORS, ids=lambda v: _json(v)["type"])
def test_vector(vector: dict[str, str]) -> None:
    frame, wire, serial = _read(vector, VERSION)
    assert encode(frame) == wire
    assert encode_stream(frame) == serial


@pytest.mark.parametrize("vector", V1_VECTORS, ids=lambda v: _json(v)["type"])
def test_version_1_vector_is_still_read(vector: dict[str, str]) -> None:
    frame, _, _ = _read(vector, 1)
    encoded = bytes.fromhex(vector["encoded"])
    assert encoded[0] == VERSION and encode(frame) == encoded  # the canonical re-encoding is version 2
    assert decode(encoded) == frame


def test_there_is_a_version_1_data_vector() -> None:
    assert any(_json(v)["type"] == "DATA" for v in V1_VECTORS)


def test_crc_vector() -> None:
    (v,) = _blocks("vector-crc")
    assert crc16(bytes.fromhex(v["input"])).to_bytes(2, "big") == bytes.fromhex(v["crc"])


def test_fragment_vectors_reassemble_to_the_datagram_vector() -> None:
    (datagram,) = _blocks("vector-datagram")
    r = Reassembler()
    fragments = [decode(bytes.fromhex(v["wire"])) for v in VECTORS if "tag" in _json(v)["payload"]]
    assert len(fragments) >= 2
    out = [f for f in (r.receive(x, 0.0) for x in fragments) if f is not None]
    assert [frame_to_json(f) for f in out] == [json.loads(datagram["frame"])]

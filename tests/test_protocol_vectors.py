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
from cellbridge.protocol.frame import HEADER_LEN
from cellbridge.decode import frame_to_json

SPEC = Path(__file__).resolve().parent.parent / "docs" / "protocol.md"
BLOCK = re.compile(r"```(vector(?:-crc|-datagram|-v1|-v2)?)\n(.*?)```", re.S)


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
V2_VECTORS = _blocks("vector-v2")
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
    # version 3's packing: a frame of several samples, one with an index skipped and a negative
    # residual, and one whose index jumps (mesh time taken); every DATA vector has its period
    assert all(p["period"] == 50_000_000 // p["rate"] for p in data)
    steps = [[b[5] - a[5] for a, b in zip(p["samples"], p["samples"][1:])] for p in data]
    assert any(len(p["samples"]) >= 5 and 2 in st for p, st in zip(data, steps))
    assert any(b[1] < a[1] + (b[5] - a[5]) * p["period"] for p in data for a, b in zip(p["samples"], p["samples"][1:]))
    assert any(s > 1000 for st in steps for s in st)


@pytest.mark.parametrize("vector", VECTORS, ids=lambda v: _json(v)["type"])
def test_vector(vector: dict[str, str]) -> None:
    frame, wire, serial = _read(vector, VERSION)
    assert encode(frame) == wire
    assert encode_stream(frame) == serial


@pytest.mark.parametrize("version,vector", [(1, v) for v in V1_VECTORS] + [(2, v) for v in V2_VECTORS],
                         ids=lambda v: _json(v)["type"] if isinstance(v, dict) else f"v{v}")
def test_an_older_version_vector_is_still_read(version: int, vector: dict[str, str]) -> None:
    frame, wire, _ = _read(vector, version)
    assert frame.payload.period == 0  # versions 1 and 2 had none: their samples are all absolute
    encoded = bytes.fromhex(vector["encoded"])
    assert encoded[0] == VERSION and encode(frame) == encoded  # the canonical re-encoding is version 3
    assert encoded[1:HEADER_LEN] == wire[1:HEADER_LEN] and decode(encoded) == frame


def test_there_are_version_2_vectors_of_every_data_kind() -> None:
    kinds = {(json.loads(v["frame"])["payload"]["mode"], bool(json.loads(v["frame"])["payload"]["samples"][0][4] & NO_MESH_TIME))
             for v in V2_VECTORS}
    assert kinds == {(0, False), (1, False), (0, True)}


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

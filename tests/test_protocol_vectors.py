"""The test vectors of docs/protocol.md, read from the document itself.

``tests/support/protocol_doc_vectors.py`` regenerates their bytes; the first test here checks that
the document holds what it would write, so a vector can neither drift from the encoder nor
be edited by hand into another truth.
"""

from __future__ import annotations

import json
import re
from typing import Any

import pytest
from cellbridge.protocol import (
    VERSION,
    Data,
    Fragment,
    Frame,
    Reassembler,
    SampleFlags,
    StreamDecoder,
    crc16,
    decode,
    encode,
    encode_stream,
)
from cellbridge.protocol.frame import CRC_LEN, HEADER_LEN

from cellbridge.decode import frame_to_json
from support.payloads import payload_as
from support.protocol_doc_vectors import SPEC, regenerate

BLOCK = re.compile(r"```(vector(?:-crc|-datagram|-v1|-v2|-v3)?)\n(.*?)```", re.S)


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
V3_VECTORS = _blocks("vector-v3")
NO_MESH_TIME = int(SampleFlags.NO_MESH_TIME)


def test_the_vectors_in_the_document_are_current() -> None:
    """What ``tests/support/protocol_doc_vectors.py`` would write is what the document holds (run it
    after a change of the encoding: ``.venv/bin/python tests/support/protocol_doc_vectors.py``)."""
    text = SPEC.read_text()
    assert len(BLOCK.findall(text)) >= 30
    assert regenerate(text) == text


def test_every_frame_type_has_a_vector() -> None:
    frames = [_json(v) for v in VECTORS]
    types = {f["type"] for f in frames}
    assert types == {"DATA", "BEACON", "HELLO", "STATUS", "CMD", "CMD_REPLY", "LINK_ACK", "BUNDLE", "READOUT",
                     "READOUT_SAME"}
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


def test_the_readout_vectors_show_every_state_and_a_record_in_parts() -> None:
    """Version 4's READOUT: a periodic record (samples only), an event-based one with samples,
    unchanged and missing elements, both parts of one record, and a bridge's on a cell with
    the step back to its reference."""
    readouts = [f for f in map(_json, VECTORS) if f["type"] == "READOUT"]
    for f in readouts:
        p = f["payload"]
        ids = [s[0] for s in p["samples"]] + p["unchanged"] + p["missing"]
        assert len(ids) == len(set(ids))
        # a gateway's record to the host, or a bridge's to its parent naming its reference
        assert (f["dst"] == 0) != bool(p["ref_step"]), f
    assert any(f["payload"]["ref_step"] for f in readouts)
    whole = [f["payload"] for f in readouts if f["payload"]["parts"] == 1]
    assert any(p["samples"] and not p["unchanged"] and not p["missing"] for p in whole)
    assert any(p["samples"] and p["unchanged"] and p["missing"] for p in whole)
    parts = [f for f in readouts if f["payload"]["parts"] == 2]
    assert sorted(f["payload"]["part"] for f in parts) == [0, 1]
    assert len({(f["origin"], f["payload"]["index"], f["payload"]["span_us"]) for f in parts}) == 1
    assert [f["seq"] for f in parts] == [parts[0]["seq"], parts[0]["seq"] + 1]  # a frame each, numbered in turn
    assert {f["payload"]["mode"] for f in parts} == {0, 1}  # split by mode
    every = [s[0] for f in parts for s in f["payload"]["samples"]] + [b for f in parts for b in
                                                                      f["payload"]["unchanged"] + f["payload"]["missing"]]
    assert len(every) == len(set(every))  # no element in two parts


@pytest.mark.parametrize("vector", VECTORS, ids=lambda v: _json(v)["type"])
def test_vector(vector: dict[str, str]) -> None:
    frame, wire, serial = _read(vector, VERSION)
    assert encode(frame) == wire
    assert encode_stream(frame) == serial


@pytest.mark.parametrize("version,vector", [(1, v) for v in V1_VECTORS] + [(2, v) for v in V2_VECTORS],
                         ids=lambda v: _json(v)["type"] if isinstance(v, dict) else f"v{v}")
def test_an_older_version_vector_is_still_read(version: int, vector: dict[str, str]) -> None:
    frame, wire, _ = _read(vector, version)
    assert payload_as(frame, Data).period == 0  # versions 1 and 2 had none: their samples are all absolute
    encoded = bytes.fromhex(vector["encoded"])
    assert encoded[0] == VERSION and encode(frame) == encoded  # the canonical re-encoding is version 4
    assert encoded[1:HEADER_LEN] == wire[1:HEADER_LEN] and decode(encoded) == frame


@pytest.mark.parametrize("vector", V3_VECTORS, ids=lambda v: _json(v)["type"])
def test_a_version_3_vector_reads_as_today(vector: dict[str, str]) -> None:
    frame, wire, _ = _read(vector, 3)
    encoded = bytes.fromhex(vector["encoded"])
    assert encode(frame) == encoded and decode(encoded) == frame
    if isinstance(frame.payload, Fragment):
        assert encoded == wire  # a fragment keeps its datagram's version
    else:
        assert encoded[0] == VERSION
        if frame.type.name != "BUNDLE":  # version 4 kept every version 3 payload
            assert encoded[1:-CRC_LEN] == wire[1:-CRC_LEN]


def test_there_are_version_3_vectors_of_data_a_beacon_a_bundle_and_a_fragment() -> None:
    shown = {(_json(v)["type"], "tag" in _json(v)["payload"]) for v in V3_VECTORS}
    assert shown == {("DATA", False), ("BEACON", False), ("BUNDLE", False), ("DATA", True)}


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

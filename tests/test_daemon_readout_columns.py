"""The daemon's compiled reader of READOUT payloads (daemon/core/readout_columns.py) against
the protocol's plain path: on every payload it gives nothing, or exactly the plain path's
record; it takes every valid record whose index fits 63 bits; it never takes what the plain
path refuses. And the skin frames made of its columns are the frames of the plain records."""

from __future__ import annotations

import dataclasses
from typing import Any

import msgpack
import numpy as np
from cellbridge.daemon.core.frames import SkinFrame, SkinFrames
from cellbridge.daemon.core.readout_columns import ReadoutColumns, readout_columns
from cellbridge.protocol import FrameType, Mode, ProtocolError, Readout, StreamDecoder, encode_stream
from cellbridge.protocol.frame import HEADER_LEN, Frame, decode, encode
from cellbridge.protocol.messages import pack_payload, unpack_payload
from cobs import cobs
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from support.protocol_strategies import readouts
from support.protocol_wire import sealed

_READOUT = int(FrameType.READOUT)
SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _plain(payload: bytes) -> Readout | None:
    try:
        r = unpack_payload(_READOUT, payload)
    except ProtocolError:
        return None
    assert isinstance(r, Readout)
    return r


def _agrees(payload: bytes) -> ReadoutColumns | None:
    """The contract: None, or the plain path's record (which must then decode)."""
    got = readout_columns(payload)
    want = _plain(payload)
    if got is not None:
        assert want is not None, payload.hex()
        assert got.readout() == want
        for a in (got.samples, got.unchanged, got.missing):
            assert a.dtype == np.int64
    return got


@SETTINGS
@given(readouts(max_elements=64), st.booleans())
def test_a_valid_record_is_read_into_the_columns_of_the_plain_record(r: Readout, old_form: bool) -> None:
    if r.ref_step:  # (a bridge's to its parent, never on a gateway's line: the plain path reads it)
        assert _agrees(msgpack.packb(r.to_wire())) is None
        r = dataclasses.replace(r, ref_step=0)
    wire = r.to_wire()
    if old_form:  # the ten fields written before the root was carried
        r = Readout(r.index, r.rate, r.mode, r.oversampling, r.samples, r.unchanged, r.missing, r.span_us, r.part,
                    r.parts)
        wire = r.to_wire()[:10]
    payload = msgpack.packb(wire)
    got = _agrees(payload)
    if r.index < 2**63:
        assert got is not None  # (a valid record never pays the plain path)
    assert ReadoutColumns.of(r).readout() == r


@st.composite
def _mutated(draw: st.DrawFn) -> bytes:
    """A valid record's payload, then bytes changed, inserted, dropped or cut."""
    payload = bytearray(pack_payload(draw(readouts(max_elements=20))))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["set", "insert", "delete", "cut"]))
        at = draw(st.integers(0, max(0, len(payload) - 1)))
        if op == "set" and payload:
            payload[at] = draw(st.integers(0, 255))
        elif op == "insert":
            payload.insert(at, draw(st.integers(0, 255)))
        elif op == "delete" and payload:
            del payload[at]
        elif op == "cut":
            del payload[at:]
    return bytes(payload)


_cell = st.one_of(st.integers(-3, 2**64 - 1), st.integers(0, 300), st.booleans(), st.none(), st.just(1.5),
                  st.binary(max_size=2))
_ids = st.lists(st.one_of(st.integers(-2, 70_000), st.booleans()), max_size=5)


@st.composite
def _shaped(draw: st.DrawFn) -> bytes:
    """A wire array shaped like a READOUT, any value in any field."""
    samples = draw(st.lists(st.lists(st.one_of(_cell, st.integers(0, 70_000)), min_size=3, max_size=5), max_size=5))
    fields = [draw(st.one_of(_cell, st.integers(0, 3))) for _ in range(4)] + [samples, draw(_ids), draw(_ids)]
    fields += [draw(st.one_of(_cell, st.integers(0, 3))) for _ in range(draw(st.integers(2, 6)))]
    return msgpack.packb(fields)


@SETTINGS
@given(st.one_of(_mutated(), _shaped(), st.binary(max_size=40)))
def test_on_any_payload_the_reader_gives_nothing_or_the_plain_record(payload: bytes) -> None:
    _agrees(payload)


def test_what_the_reader_leaves_to_the_plain_path() -> None:
    """Not canonical, an index beyond 63 bits, a bridge in two lists: None (the plain path decides)."""
    r = Readout(5, 100, Mode.COUNTER, 1, (), (1, 2), (3,), 10, 0, 1, 0)
    ok = pack_payload(r)
    assert _agrees(ok) is not None
    assert _agrees(bytes([0xDC, 0, 11]) + ok[1:]) is None  # an array16 header for 11 fields: not canonical
    assert _agrees(pack_payload(Readout(2**63, 100, Mode.COUNTER, 1, (), (), ()))) is None  # plain decodes it
    assert _plain(pack_payload(Readout(2**63, 100, Mode.COUNTER, 1, (), (), ()))) is not None
    assert _agrees(msgpack.packb([5, 100, 0, 1, [], [1, 2], [2], 10, 0, 1, 0])) is None
    assert _agrees(ok + b"\x00") is None


def test_a_frame_decoded_with_the_reader_is_the_plain_frame_with_columns() -> None:
    r = Readout(7, 100, Mode.ADC, 4, (), (9,), (), 4000, 0, 1, 3, 1200)
    raw = encode(Frame(12, 0, 12, 5, r))
    got: Any = decode(raw, readout_columns).payload  # (the reader's own form, not a Message)
    assert type(got) is ReadoutColumns and got.readout() == r
    assert decode(raw).payload == r


@SETTINGS
@given(st.lists(st.one_of(readouts(max_elements=12), _mutated()), min_size=1, max_size=6))
def test_a_stream_counts_every_frame_alike_with_and_without_the_reader(items: list[Any]) -> None:
    """The same bytes, the same frames delivered and the same drops by cause."""
    stream = b""
    for i, x in enumerate(items):
        if isinstance(x, Readout):
            stream += encode_stream(Frame(3, 0, 3, i, x))
        else:  # a payload the CRC passes, valid or not
            head = encode(Frame(3, 0, 3, i, Readout(1, 100, Mode.COUNTER, 1, ())))[:HEADER_LEN]
            stream += cobs.encode(sealed(head + x)) + b"\x00"
    plain, fast = StreamDecoder(), StreamDecoder(readout=readout_columns)
    a, b = plain.feed(stream), fast.feed(stream)
    assert plain.counters() == fast.counters()
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert (x.src, x.origin, x.seq) == (y.src, y.origin, y.seq)
        got: Any = y.payload
        assert (got.readout() if type(got) is ReadoutColumns else got) == x.payload


def _same(f: SkinFrame, g: SkinFrame) -> None:
    for name in SkinFrame.__slots__:
        a, b = getattr(f, name), getattr(g, name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b), name
        else:
            assert a == b, name


@SETTINGS
@given(st.lists(st.tuples(st.integers(1, 3), st.integers(0, 4), readouts(max_elements=8), st.integers(1, 2)),
                max_size=12))
def test_skin_frames_of_columns_are_the_frames_of_the_plain_records(
        recs: list[tuple[int, int, Readout, int]]) -> None:
    """Records of a few frames from three gateways (parts, overlaps, gaps, conflicts as they
    fall): fed as plain records or as their columns, the same frames and counts."""
    plain, cols = SkinFrames(0.01), SkinFrames(0.01)
    for i, (gw, k, r, parts) in enumerate(recs):
        r = Readout(k, 100, r.mode, r.oversampling, r.samples, r.unchanged, r.missing, 2000, i % parts, parts)
        now = k / 100 + 0.003 + 0.001 * i
        plain.add(gw, r, now, k / 100)
        cols.add(gw, ReadoutColumns.of(r), now, k / 100)
    got_plain, got_cols = plain.take(10.0), cols.take(10.0)
    assert len(got_plain) == len(got_cols)
    for f, g in zip(got_plain, got_cols):
        _same(f, g)
    assert plain.counts == cols.counts


def test_the_warm_up_loads_the_reader_and_a_reader_that_fails_leaves_every_record_to_the_plain_path(monkeypatch) -> None:
    """The daemon warms the reader before its links start (its first READOUT compiled it on
    the event loop: 0.4 s from the cache, 4 s on a fresh installation). A reader that cannot
    be compiled is not tried again (numba retries a failed compile at every call: seconds a
    record), and the plain path reads the records, the same."""
    from cellbridge.daemon.core import readout_columns as rc

    assert rc.warm_up() is True
    rec = Readout(7, 100, Mode.COUNTER, 1, (), (4, 5), (), 10, 0, 1, 1, 1)
    payload = pack_payload(rec)
    assert readout_columns(payload) is not None
    calls = []

    def broken(buf: Any) -> Any:
        calls.append(1)
        raise TypeError("cannot compile")

    monkeypatch.setattr(rc, "_PARSE", [broken])
    monkeypatch.setattr(rc, "_USABLE", [True])
    assert readout_columns(payload) is None and readout_columns(payload) is None
    assert len(calls) == 1  # not tried again
    assert rc.warm_up() is False
    wire = encode(Frame(3, 0, 3, 1, rec))
    assert decode(wire, readout_columns).payload == rec  # the plain path's record

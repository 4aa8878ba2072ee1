"""READOUT (protocol version 4, docs/protocol.md §4): one skin frame as a subtree read it out.

Every element routed through the sender is in exactly one state: a sample, unchanged or
missing. The decoder accepts a record only in its one canonical form (each list strictly
increasing by bridge id, a bridge in one list), with samples the chip can produce in the
record's mode and only the overflow flags, and ``part`` below ``parts``; anything else is
dropped with cause ``payload``. Frames older than version 4 had no READOUT: ``type``.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any

import msgpack
import pytest
from cellbridge.protocol import (
    MAX_FRAME,
    VERSION,
    Fragment,
    Frame,
    FrameType,
    HostReceiver,
    Mode,
    ProtocolError,
    Readout,
    ReadoutSample,
    Reassembler,
    SampleFlags,
    StreamDecoder,
    decode,
    encode,
    fragment,
)
from cellbridge.protocol.frame import HEADER_LEN
from cobs import cobs
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from support.payloads import payload_as
from support.protocol_strategies import readouts
from support.protocol_v1 import encode_old
from support.protocol_wire import sealed

U16, U32, U64 = 0xFFFF, 2**32 - 1, 2**64 - 1
SAMPLES, UNCHANGED, MISSING = 4, 5, 6  # positions of the three lists in the wire array
LISTS = (SAMPLES, UNCHANGED, MISSING)
#: a READOUT frame's header, version 4: gateway 1 to the host
HEAD = encode(Frame(1, 0, 1, 7, Readout(1, 100, Mode.COUNTER, 1, ())))[:HEADER_LEN]
SETTINGS = settings(max_examples=200, suppress_health_check=[HealthCheck.too_slow])


def _decode_payload(obj: Any) -> Readout:
    """The READOUT a receiver reads from the wire array ``obj`` (in a version 4 frame)."""
    payload = decode(sealed(HEAD + msgpack.packb(obj))).payload
    assert isinstance(payload, Readout)
    return payload


def _refused(obj: Any) -> ProtocolError:
    with pytest.raises(ProtocolError) as err:
        _decode_payload(obj)
    assert err.value.cause == "payload"
    return err.value


def _ids(obj: list[Any], where: int) -> list[int]:
    return [s[0] for s in obj[where]] if where == SAMPLES else list(obj[where])


def _with_id(obj: list[Any], where: int, ids: list[int]) -> list[Any]:
    """``obj`` with the bridge ids of list ``where`` replaced (samples keep their readings)."""
    out = copy.deepcopy(obj)
    if where == SAMPLES:
        readings = out[SAMPLES] + [[0, 100, 100, 0]] * max(0, len(ids) - len(out[SAMPLES]))
        out[SAMPLES] = [[b, *r[1:]] for b, r in zip(ids, readings)]
    else:
        out[where] = ids
    return out


def _valid_elements(r: Readout) -> bool:
    ids = [s.bridge for s in r.samples] + list(r.unchanged) + list(r.missing)
    return all(list(x) == sorted(set(x)) for x in ([s.bridge for s in r.samples], r.unchanged, r.missing)) \
        and len(ids) == len(set(ids))


@SETTINGS
@given(readouts(max_elements=64))
def test_a_readout_round_trips_whole_or_fragmented(r: Readout) -> None:
    assert Readout.from_wire(msgpack.unpackb(msgpack.packb(r.to_wire()))) == r
    frame = Frame(1, 0, 1, 40_000, r, 0, 0)
    try:
        wire = encode(frame)
    except ProtocolError as exc:  # a subtree too large for one frame: it travels fragmented
        assert exc.cause == "too_large"
        pieces = fragment(frame, tag=9)
        assert len(pieces) > 1 and all(p.payload.frame_type is FrameType.READOUT for p in pieces)
        rx = Reassembler()
        assert [w for w in (rx.receive(decode(encode(p)), 0.0) for p in pieces) if w] == [frame]
        return
    assert wire[0] == VERSION == 4 and wire[2] == FrameType.READOUT.value == 9
    got = decode(wire)
    assert got == frame and encode(got) == wire  # one record, one byte string
    assert payload_as(got, Readout).bridges() == len(r.samples) + len(r.unchanged) + len(r.missing)
    assert _valid_elements(payload_as(got, Readout))


@SETTINGS
@given(readouts(), st.data())
def test_bridge_ids_out_of_order_or_repeated_in_a_list_are_refused(r: Readout, data: st.DataObject) -> None:
    obj = r.to_wire()
    where = data.draw(st.sampled_from([w for w in LISTS if len(_ids(obj, w)) >= 2] or [SAMPLES]))
    ids = _ids(obj, where)
    if len(ids) < 2:  # too short to disorder: repeat the one id there is, or add two equal
        ids = (ids or [5]) * 2
    else:
        i = data.draw(st.integers(0, len(ids) - 2))
        if data.draw(st.booleans()):
            ids[i], ids[i + 1] = ids[i + 1], ids[i]  # two neighbours swapped
        else:
            ids[i + 1] = ids[i]  # one id twice
    bad = _with_id(obj, where, ids)
    assume(_ids(bad, where) != sorted(set(_ids(bad, where))))
    _refused(bad)


@SETTINGS
@given(readouts(), st.data())
def test_a_bridge_in_two_lists_is_refused(r: Readout, data: st.DataObject) -> None:
    obj = r.to_wire()
    assume(r.bridges() > 0)
    source = data.draw(st.sampled_from([w for w in LISTS if obj[w]]))
    target = data.draw(st.sampled_from([w for w in LISTS if w != source]))
    b = data.draw(st.sampled_from(_ids(obj, source)))
    ids = sorted([*_ids(obj, target), b])  # in order in its second list: only the repeat is wrong
    err = _refused(_with_id(obj, target, ids))
    assert f"bridge {b} is in two states" in err.detail


@pytest.mark.parametrize("part,parts", [(1, 1), (2, 2), (5, 3), (255, 255), (0, 0), (0, 256), (-1, 2), (0, -1)])
def test_a_part_not_below_parts_is_refused(part: int, parts: int) -> None:
    good = Readout(4521, 100, Mode.COUNTER, 1, (ReadoutSample(2, 19600, 15800),), (3,), (4,), 2840, 0, 1).to_wire()
    assert _decode_payload(good).parts == 1
    bad = copy.deepcopy(good)
    bad[8:10] = [part, parts]
    _refused(bad)


@given(readouts(), st.integers(0, 0xFF), st.integers(0, 0xFF))
def test_any_part_not_below_parts_is_refused(r: Readout, part: int, parts: int) -> None:
    assume(part >= parts)
    bad = r.to_wire()
    bad[8:10] = [part, parts]
    _refused(bad)


@given(st.integers(1, 255).flatmap(lambda n: st.tuples(st.integers(0, n - 1), st.just(n))))
def test_every_part_below_parts_is_read(pp: tuple[int, int]) -> None:
    part, parts = pp
    got = _decode_payload(Readout(7, 250, Mode.COUNTER, 1, (), (9,), (), 0, part, parts).to_wire())
    assert (got.part, got.parts) == pp


def _sample_wire(mode: int, over: int, c1: int, c2: int = 0, flags: int = 0) -> list[Any]:
    return [4521, 100, mode, over, [[2, c1, c2, flags]], [], [], 2840, 0, 1]


@pytest.mark.parametrize("mode,over,c1", [
    (0, 1, 0x10000),  # counter: 16-bit counts
    (1, 1, 256),  # ADC: one 8-bit code
    (1, 16, 255 * 16 + 1),  # ADC: the sum of 16 codes
    (1, 0xFFFF, 255 * 0xFFFF + 1),
])
def test_codes_beyond_the_mode_are_refused(mode: int, over: int, c1: int) -> None:
    assert _decode_payload(_sample_wire(mode, over, c1 - 1, c1 - 1)).samples[0].c1 == c1 - 1
    _refused(_sample_wire(mode, over, c1))
    _refused(_sample_wire(mode, over, 0, c1))


@given(readouts(), st.data())
def test_any_code_beyond_the_records_mode_is_refused(r: Readout, data: st.DataObject) -> None:
    """A counter counts to 65535, an ADC sum to 255 per conversion: a sample above its
    record's mode is one no chip produced (or one read in another mode: another part)."""
    assume(r.samples)
    limit = 0xFFFF if r.mode is Mode.COUNTER else 255 * r.oversampling
    bad = r.to_wire()
    sample = bad[SAMPLES][data.draw(st.integers(0, len(r.samples) - 1))]
    sample[data.draw(st.sampled_from([1, 2]))] = limit + data.draw(st.integers(1, 2**32))
    _refused(bad)


@pytest.mark.parametrize("mode,over", [
    (0, 2), (0, 0), (0, True), (0, 1.0),  # counter mode: oversampling is 1
    (1, 0), (1, 0x10000), (1, -1), (1, None),  # ADC: 1..65535 conversions
    (2, 1), (-1, 1), (True, 1), (None, 1),  # no such mode
])
def test_wrong_mode_or_oversampling_is_refused(mode: Any, over: Any) -> None:
    _refused(_sample_wire(mode, over, 5))


@pytest.mark.parametrize("flags", [0, 1, 2, 3])
def test_the_overflow_flags_are_read(flags: int) -> None:
    assert _decode_payload(_sample_wire(0, 1, 19600, 15800, flags)).samples[0].flags == flags


@given(st.integers(4, 255))
def test_flags_beyond_the_overflow_bits_are_refused(flags: int) -> None:
    """NO_MESH_TIME has no place in a readout (a bridge without mesh time has no slot: it is
    missing), nor HELD (the unchanged state says it), nor the undefined bits 4-7."""
    _refused(_sample_wire(0, 1, 19600, 15800, flags))


def test_no_mesh_time_and_held_are_refused_by_name() -> None:
    for flag in (SampleFlags.NO_MESH_TIME, SampleFlags.HELD, SampleFlags.HELD | SampleFlags.OVERFLOW_C1):
        _refused(_sample_wire(0, 1, 19600, 15800, int(flag)))


GOOD = Readout(4521, 100, Mode.COUNTER, 1, (ReadoutSample(2, 19600, 15800, 1), ReadoutSample(130, 19000, 15000)),
               (3, 300), (4,), 2840, 0, 1, 7).to_wire()


def _replaced(path: tuple[int, ...], value: Any) -> list[Any]:
    out = copy.deepcopy(GOOD)
    parent = out
    for i in path[:-1]:
        parent = parent[i]
    if value is ...:
        del parent[path[-1]]
    else:
        parent[path[-1]] = value
    return out


#: GOOD with one field wrong (its comment); every other field as in GOOD
BAD = [
    (GOOD[:9], "9 fields"), (GOOD + [0], "12 fields with age 0: 0 is said by leaving it out"), ({"index": 1}, "a map"), ([], "empty"),
    (_replaced((0,), -1), "negative index"), (_replaced((0,), -(2**63)), "index a signed 64-bit"),
    (_replaced((0,), None), "nil index"), (_replaced((0,), True), "bool index"),
    (_replaced((1,), 0), "rate 0: a readout exists only on mesh time"), (_replaced((1,), 0x10000), "rate beyond u16"),
    (_replaced((7,), 2**32), "span beyond u32"), (_replaced((7,), -1), "negative span"),
    (_replaced((7,), 1.5), "float span"),
    (_replaced((4,), None), "samples nil"), (_replaced((5,), {}), "unchanged a map"), (_replaced((6,), 4), "missing an int"),
    (_replaced((4, 0), [2, 19600, 15800]), "sample of 3 fields"), (_replaced((4, 0), [2, 19600, 15800, 0, 0]), "of 5"),
    (_replaced((4, 0), 2), "sample not an array"), (_replaced((4, 0, 0), 0x10000), "bridge beyond u16"),
    (_replaced((4, 0, 0), -1), "negative bridge"), (_replaced((4, 0, 1), -1), "negative c1"),
    (_replaced((4, 0, 2), None), "nil c2"), (_replaced((4, 0, 3), True), "bool flags"),
    (_replaced((5, 0), -3), "negative unchanged id"), (_replaced((5, 1), 0x10000), "unchanged id beyond u16"),
    (_replaced((6, 0), 4.0), "float missing id"), (_replaced((6, 0), False), "bool missing id"),
    (_replaced((6, 0), [4]), "missing id an array"),
]


@pytest.mark.parametrize("obj,why", BAD, ids=[why for _, why in BAD])
def test_a_malformed_readout_is_refused(obj: Any, why: str) -> None:
    assert _decode_payload(GOOD).bridges() == 5  # the well-formed neighbour reads
    _refused(obj)


def test_a_readout_without_its_root_reads_as_root_0_and_a_root_past_u16_is_refused() -> None:
    """The 10-field form (records written before the root was carried) still reads."""
    assert Readout.from_wire(GOOD).root == 7
    assert Readout.from_wire(GOOD[:10]) == dataclasses.replace(Readout.from_wire(GOOD), root=0)
    for root in (-1, 0x10000, 1.0, None):
        with pytest.raises(ProtocolError):
            Readout.from_wire(GOOD[:10] + [root])


def test_a_gateways_readout_says_its_age_and_an_age_out_of_u32_or_zero_is_refused() -> None:
    """The 12-field form: a gateway's record with the µs since its frame's gates started.
    Written only when said, so a record without it keeps its 11 fields, byte for byte."""
    aged = Readout.from_wire(GOOD + [9392])
    assert aged == dataclasses.replace(Readout.from_wire(GOOD), age_us=9392)
    assert aged.to_wire() == GOOD + [9392] and Readout.from_wire(GOOD).to_wire() == GOOD
    assert Readout.from_wire(GOOD + [0xFFFF_FFFF]).age_us == 0xFFFF_FFFF
    for age in (0, -1, 2**32, 1.5, None, True):
        with pytest.raises(ProtocolError):
            Readout.from_wire(GOOD + [age])
    with pytest.raises(ProtocolError):
        Readout.from_wire(GOOD + [9392, 0])


def test_a_bridges_readout_says_the_step_to_its_reference_and_a_step_out_of_1_to_127_is_refused() -> None:
    """The 13-field form: a bridge's record to its parent with ``ref_step`` after a zero
    age (a gateway's record never says it: its 11 or 12 fields stay byte for byte)."""
    stepped = Readout.from_wire(GOOD + [0, 6])
    assert stepped == dataclasses.replace(Readout.from_wire(GOOD), ref_step=6)
    assert stepped.to_wire() == GOOD + [0, 6]
    assert Readout.from_wire(GOOD + [9392, 127]).age_us == 9392
    for step in (0, 128, -1, 1.0, None, True):
        with pytest.raises(ProtocolError):
            Readout.from_wire(GOOD + [0, step])
    for age in (-1, 2**32, None):
        with pytest.raises(ProtocolError):
            Readout.from_wire(GOOD + [age, 6])
    with pytest.raises(ProtocolError):
        Readout.from_wire(GOOD + [0, 6, 0])


def test_a_readout_with_trailing_bytes_or_a_wider_form_is_refused() -> None:
    body = HEAD + msgpack.packb(GOOD)
    assert decode(sealed(body)).payload == Readout.from_wire(GOOD)
    for bad in (body + b"\x00", body.replace(b"\x9b", b"\xdc\x00\x0b", 1), HEAD + msgpack.packb(GOOD + [0])):
        with pytest.raises(ProtocolError) as err:
            decode(sealed(bad))
        assert err.value.cause == "payload"


# -- versions ------------------------------------------------------------------------------


@pytest.mark.parametrize("version", [1, 2, 3])
def test_a_readout_in_a_frame_older_than_version_4_is_an_unknown_type(version: int) -> None:
    frame = Frame(1, 0, 1, 7, Readout.from_wire(GOOD))
    wire = encode_old(frame, version)
    assert wire[0] == version and wire[1:] != encode(frame)[1:]  # the same frame, another version
    with pytest.raises(ProtocolError) as err:
        decode(wire)
    assert err.value.cause == "type" and f"version {version}" in err.value.detail
    decoder = StreamDecoder()
    assert decoder.feed(b"\x00" + cobs.encode(wire) + b"\x00" + cobs.encode(encode(frame)) + b"\x00") == [frame]
    assert decoder.frames_dropped == {"type": 1}


@pytest.mark.parametrize("version", [1, 2, 3])
def test_a_fragment_of_a_readout_older_than_version_4_is_an_unknown_type(version: int) -> None:
    piece = fragment(Frame(1, 0, 1, 7, Readout(9, 100, Mode.COUNTER, 1, (), tuple(range(1, 200)))), tag=3)[0]
    wire = bytearray(encode(piece))
    wire[0] = version
    with pytest.raises(ProtocolError) as err:
        decode(sealed(bytes(wire[:-2])))
    assert err.value.cause == "type"


@pytest.mark.parametrize("version", [1, 2, 3])
def test_a_fragment_of_a_readout_older_than_version_4_cannot_be_encoded(version: int) -> None:
    """What decode drops is never written: before this check encode wrote the fragment."""
    with pytest.raises(ProtocolError) as err:
        encode(Frame(1, 0, 1, 7, Fragment(FrameType.READOUT, 3, 0, 10, b"abc", version)))
    assert err.value.cause == "type"
    assert payload_as(decode(encode(Frame(1, 0, 1, 7, Fragment(FrameType.READOUT, 3, 0, 10, b"abc", 4)))), Fragment).version == 4


# -- sizes (docs/protocol.md §4, READOUT: cost per element) ---------------------------------


def _frame_len(r: Readout) -> int:
    return len(encode(Frame(1, 0, 1, 7, r)))


@pytest.mark.parametrize("bridge,cost", [(1, 9), (127, 9), (128, 10), (255, 10), (256, 11), (0xFFFE, 11)])
def test_a_counter_sample_costs_9_to_11_bytes_by_its_bridge_id(bridge: int, cost: int) -> None:
    base = Readout(4521, 100, Mode.COUNTER, 1, (), span_us=2840)
    one = Readout(4521, 100, Mode.COUNTER, 1, (ReadoutSample(bridge, 19600, 15800),), span_us=2840)
    assert _frame_len(one) - _frame_len(base) == cost


@pytest.mark.parametrize("bridge,cost", [(1, 1), (127, 1), (128, 2), (255, 2), (256, 3), (0xFFFE, 3)])
def test_an_unchanged_or_missing_element_costs_1_to_3_bytes(bridge: int, cost: int) -> None:
    base = Readout(4521, 100, Mode.COUNTER, 1, (), span_us=2840)
    assert _frame_len(Readout(4521, 100, Mode.COUNTER, 1, (), (bridge,), span_us=2840)) - _frame_len(base) == cost
    assert _frame_len(Readout(4521, 100, Mode.COUNTER, 1, (), (), (bridge,), span_us=2840)) - _frame_len(base) == cost


def test_what_one_frame_holds() -> None:
    """A periodic 4x4 fits one frame; a frame holds 24 counter samples or 173 unchanged ids
    (ids below 128, index past 2^16, span in 16 bits); an 8x8 periodic record does not fit."""
    def periodic(n: int) -> Readout:
        return Readout(2**20, 100, Mode.COUNTER, 1, tuple(ReadoutSample(b, 19600, 15800) for b in range(1, n + 1)),
                       span_us=3000)
    assert _frame_len(periodic(16)) == 180
    assert _frame_len(periodic(24)) <= MAX_FRAME
    with pytest.raises(ProtocolError):
        _frame_len(periodic(25))
    idle = Readout(2**20, 100, Mode.COUNTER, 1, (), tuple(range(1, 174)), span_us=3000)
    assert _frame_len(idle) <= MAX_FRAME
    with pytest.raises(ProtocolError):
        _frame_len(Readout(2**20, 100, Mode.COUNTER, 1, (), tuple(range(1, 175)), span_us=3000))
    assert len(fragment(Frame(1, 0, 1, 7, periodic(64)), tag=1)) == 3


# -- the host's receive path ---------------------------------------------------------------


def test_the_host_delivers_every_part_of_a_record_once_and_reassembles_a_fragmented_one() -> None:
    """A READOUT passes the host like DATA: each part is a frame of its own (its own seq),
    a copy (a second gateway, or a replay) is dropped, and a record sent fragmented is
    delivered once whole, even when its fragments arrive twice and out of order."""
    part0 = Frame(1, 0, 1, 10, Readout(4600, 100, Mode.COUNTER, 1, (ReadoutSample(2, 19600, 15800),), (4,), (),
                                       2840, 0, 2))
    part1 = Frame(1, 0, 1, 11, Readout(4600, 100, Mode.ADC, 16, (ReadoutSample(9, 2272, 1968),), (), (10,),
                                       2840, 1, 2))
    big = Frame(1, 0, 1, 12, Readout(4601, 100, Mode.COUNTER, 1,
                                     tuple(ReadoutSample(b, 19600 + b, 15800) for b in range(1, 65)), span_us=5200))
    pieces = [decode(encode(p)) for p in fragment(big, tag=1)]
    assert len(pieces) == 3
    rx = HostReceiver()
    got = [f for t, frame in enumerate([part0, part1, part0, pieces[0], pieces[2], pieces[0], pieces[1], pieces[2],
                                        part1, pieces[1]]) for f in rx.receive(frame, t * 0.001)]
    assert got == [part0, part1, big]
    counters: dict[str, Any] = rx.counters()  # nested counts, read as the test knows them
    assert counters["dedupe"]["duplicates"] == 2  # part0 and part1 again
    assert counters["reassembly"]["drops"].get("duplicate_fragment", 0) + \
        counters["reassembly"]["drops"].get("late_duplicate", 0) == 3


_any_ids = st.lists(st.one_of(st.integers(-2, 70_000), st.booleans(), st.floats(0, 9), st.text(max_size=1)), max_size=6)
_cells = st.one_of(st.integers(-2, 300), st.booleans(), st.just(1.0), st.none())
_raw_samples = st.lists(st.one_of(st.lists(_cells, min_size=3, max_size=5), st.integers(0, 3)), max_size=6)


@settings(max_examples=600, deadline=None)
@given(_raw_samples, _any_ids, _any_ids, st.sampled_from([255, 65_535]))
def test_the_column_check_of_a_readout_agrees_with_the_element_by_element_one(
        raw: list[Any], unchanged: list[Any], missing: list[Any], limit: int) -> None:
    """A READOUT's lists are checked in a few passes over the columns (a thousand elements a
    frame): whatever they accept, the element-by-element check accepts alike, and whatever
    it accepts, they do (so no valid record pays the slow path, and no bad one slips by)."""
    from cellbridge.protocol.messages import (
        _column_readout_lists,
        _few_readout_lists,
        _readout_lists,
        _readout_lists_checked,
    )

    try:
        want = _readout_lists_checked(raw, unchanged, missing, limit)
    except ProtocolError:
        want = None
    for check in (_readout_lists, _few_readout_lists, _column_readout_lists):  # (the one pass, for few samples)
        got = check(raw, unchanged, missing, limit)
        assert got == want, check.__name__
        if got is not None:
            assert all(type(s) is ReadoutSample for s in got[0])


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(0, 65_535), unique=True, max_size=40).map(sorted), st.data())
def test_the_column_check_accepts_valid_lists_and_refuses_a_repeat(ids: list[int], data: st.DataObject) -> None:
    """Valid lists (as a gateway writes them) pass the column check; a repeated bridge fails it."""
    from cellbridge.protocol.messages import _column_readout_lists, _few_readout_lists, _readout_lists

    k = data.draw(st.integers(0, len(ids)))
    raw = [[b, 1, 2, 0] for b in ids[:k]]
    for check in (_readout_lists, _few_readout_lists, _column_readout_lists):
        got = check(raw, ids[k:], [], 65_535)
        assert got is not None and [s.bridge for s in got[0]] == ids[:k] and list(got[1]) == ids[k:]
        if ids:
            assert check(raw, ids[k:], [ids[0]], 65_535) is None


_good_row = st.lists(st.integers(0, 3), min_size=4, max_size=4)
_odd_row = st.one_of(st.binary(min_size=4, max_size=4), st.text(min_size=4, max_size=4),
                     st.tuples(*[st.integers(0, 3)] * 4), st.lists(st.integers(0, 3), min_size=3, max_size=5))


@settings(max_examples=400, deadline=None)
@given(st.lists(_good_row, max_size=5), _odd_row, st.data())
def test_the_column_check_refuses_a_sample_not_a_list_of_four_among_lists_of_four(
        rows: list[Any], odd: Any, data: st.DataObject) -> None:
    """A sample that is bytes or text of four (whose items look like ids or codes), a tuple,
    or a list of another length, among valid lists of four: the column check agrees with the
    element-by-element one (a list of four is judged alike by both; anything else fails both)."""
    from cellbridge.protocol.messages import (
        _column_readout_lists,
        _few_readout_lists,
        _readout_lists,
        _readout_lists_checked,
    )

    raw = [[b, *r[1:]] for b, r in enumerate(rows)]
    at = data.draw(st.integers(0, len(raw)))
    raw.insert(at, odd)
    try:
        want = _readout_lists_checked(raw, [], [], 255)
    except ProtocolError:
        want = None
    for check in (_readout_lists, _few_readout_lists, _column_readout_lists):
        assert check(raw, [], [], 255) == want, check.__name__
    if not (type(odd) is list and len(odd) == 4):
        assert want is None

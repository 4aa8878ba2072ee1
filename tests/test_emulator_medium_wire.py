"""The datagrams between bridge processes and the medium process."""

from __future__ import annotations

from cellbridge.emulator.medium.medium_wire import (
    CARRIER,
    RX,
    TX,
    WANT,
    decode_carrier,
    decode_rx,
    decode_tx,
    decode_want,
    encode_carrier,
    encode_rx,
    encode_tx,
    encode_want,
    sender,
)
from hypothesis import given
from hypothesis import strategies as st

cells = st.lists(st.integers(0, 2**32 - 1), min_size=1, max_size=255).map(tuple)
ids = st.integers(0, 2**32 - 1)


ticks = st.integers(0, 2**64 - 1)


@given(ids, cells, st.binary(max_size=300), st.booleans(), ticks)
def test_tx_round_trips(bridge: int, cs: tuple[int, ...], frame: bytes, want: bool, start: int) -> None:
    msg = encode_tx(bridge, cs, frame, want, start)
    assert msg[0] == TX and sender(msg) == bridge
    assert decode_tx(msg) == (bridge, cs, frame, want, start)


@given(ids, st.booleans())
def test_want_round_trips(bridge: int, on: bool) -> None:
    msg = encode_want(bridge, on)
    assert msg[0] == WANT and sender(msg) == bridge and decode_want(msg) == (bridge, on)


@given(st.integers(0, 2**32 - 1), st.integers(0, 2**64 - 1), st.integers(0, 2**64 - 1))
def test_carrier_round_trips(cell: int, start: int, end: int) -> None:
    msg = encode_carrier(cell, start, end)
    assert msg[0] == CARRIER and decode_carrier(msg) == (cell, start, end)


@given(st.integers(0, 2**32 - 1), st.binary(max_size=300), ticks)
def test_rx_round_trips(cell: int, frame: bytes, start: int) -> None:
    msg = encode_rx(cell, frame, start)
    assert msg[0] == RX and decode_rx(msg) == (cell, frame, start)


@given(st.binary(max_size=40))
def test_malformed_messages_decode_to_none_never_raise(junk: bytes) -> None:
    for decode in (decode_tx, decode_want, decode_carrier, decode_rx, sender):
        got = decode(junk)
        assert got is None or isinstance(got, (tuple, int))


def test_a_message_of_one_kind_is_not_decoded_as_another() -> None:
    # every message now travels on one socket: the kind byte must be checked
    assert decode_rx(encode_carrier(1, 2, 3)) is None
    assert decode_carrier(encode_rx(1, b"x" * 16)) is None
    assert decode_tx(encode_want(1, True)) is None
    assert decode_want(encode_tx(1, (1,), b"", True)[:6]) is None


def test_truncated_tx_is_refused() -> None:
    msg = encode_tx(7, (1, 2, 3), b"", True)
    assert decode_tx(msg[:-1]) is None  # a cell cut short
    start = bytes(8)
    assert decode_tx(b"t\x00\x00\x00\x071" + start + b"\x00") is None  # no cells
    assert decode_tx(b"t\x00\x00\x00\x07x" + start + b"\x01\x00\x00\x00\x01") is None  # want neither 0 nor 1
    assert decode_tx(b"t\x00\x00\x00\x071" + start + b"\x01\x00\x00\x00\x01") is not None  # the same, well formed
    assert decode_want(b"w\x00\x00\x00\x07x") is None

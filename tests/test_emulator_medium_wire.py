"""The one-frame messages between bridge processes and the medium process."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from cellbridge.emulator.medium_wire import (
    CARRIER, RX, TX, decode_carrier, decode_rx, decode_tx, encode_carrier, encode_rx, encode_tx,
)

cells = st.lists(st.integers(0, 2**32 - 1), min_size=1, max_size=255).map(tuple)


@given(cells, st.binary(max_size=300), st.booleans())
def test_tx_round_trips(cs: tuple[int, ...], frame: bytes, want: bool) -> None:
    msg = encode_tx(cs, frame, want)
    assert msg[0] == TX
    assert decode_tx(msg) == (cs, frame, want)


@given(st.integers(0, 2**32 - 1), st.integers(0, 2**64 - 1), st.integers(0, 2**64 - 1))
def test_carrier_round_trips(cell: int, start: int, end: int) -> None:
    msg = encode_carrier(cell, start, end)
    assert msg[0] == CARRIER and decode_carrier(msg) == (cell, start, end)


@given(st.integers(0, 2**32 - 1), st.binary(max_size=300))
def test_rx_round_trips(cell: int, frame: bytes) -> None:
    msg = encode_rx(cell, frame)
    assert msg[0] == RX and decode_rx(msg) == (cell, frame)


@given(st.binary(max_size=40))
def test_malformed_messages_decode_to_none_never_raise(junk: bytes) -> None:
    for decode in (decode_tx, decode_carrier, decode_rx):
        got = decode(junk)
        assert got is None or isinstance(got, tuple)


def test_truncated_tx_is_refused() -> None:
    msg = encode_tx((1, 2, 3), b"", True)
    assert decode_tx(msg[:-1]) is None  # a cell cut short
    assert decode_tx(b"t1\x00") is None  # no cells
    assert decode_tx(b"tx\x01\x00\x00\x00\x01") is None  # want neither 0 nor 1

"""A deferred link acknowledgement, and one queued behind it, still reach their sender
within its ack wait (the ack deferral of :mod:`~cellbridge.emulator.firmware.transceiver`)."""

from __future__ import annotations

import random

from cellbridge.emulator.firmware.linklayer import LinkLayer
from cellbridge.emulator.firmware.transceiver import Transceiver

BIT = 50
SIFS = 12 * BIT
ACK = bytes(24)  # the acknowledgement size the link layer's wait is made for


def _ends(radio: Transceiver, more_carrier: bool) -> list[int]:
    """Run the radio's acks out; with ``more_carrier`` a frame starts arriving on cell 4
    just before the first ack ends (it would end one largest frame later)."""
    ends: list[int] = []
    for _ in range(10):
        t = radio.next_tick
        if t is None:
            break
        if radio.advance(t) is not None:
            ends.append(radio.tx_until)
            if more_carrier and len(ends) == 1:
                radio.carrier(4, radio.tx_until - 20 * BIT, radio.tx_until + radio.ack_defer)
    return ends


def _sender_deadline(frame_end: int) -> int:
    """When the sender of a frame that ended at ``frame_end`` gives up on its ack."""
    sender = LinkLayer(9, (1,), Transceiver(random.Random(0)))
    return frame_end + sender._ack_wait


def _two_acks_behind_a_full_deferral(more_carrier: bool) -> tuple[list[int], int]:
    """Frames on cells 1 and 2 end together at 20 000; one on cell 3 arrives until the
    first ack's deferral ends: the two acks' ends, and their senders' deadline."""
    radio = Transceiver(random.Random(2))
    end = 20_000
    radio.carrier(3, 15_000, end + SIFS + radio.ack_defer)
    radio.send_ack(ACK, (1,), end)
    radio.send_ack(ACK, (2,), end)
    ends = _ends(radio, more_carrier)
    assert len(ends) == 2
    return ends, _sender_deadline(end)


def test_two_acks_behind_a_full_deferral_both_end_within_their_senders_ack_wait() -> None:
    # The second ack goes SIFS after the first, which went SIFS after the frame on cell 3.
    ends, deadline = _two_acks_behind_a_full_deferral(False)
    assert max(ends) < deadline, [e - deadline for e in ends]


def test_the_second_ack_does_not_defer_again_past_its_own_frames_bound() -> None:
    # The first ack deferred 100 bits; when the second was due, a frame arriving on cell 4
    # deferred it again, its bound counted from the first ack's end instead of its own
    # frame's: it ended 5 800 cycles after its sender's deadline (behind a first ack
    # deferred in full, 104 200 cycles: 2 ms), and the sender retransmits a frame the
    # bridge has (and learns a longer ack wait from it).
    radio = Transceiver(random.Random(2))
    end = 20_000
    radio.carrier(3, 15_000, end + SIFS + 100 * BIT)
    radio.send_ack(ACK, (1,), end)
    radio.send_ack(ACK, (2,), end)
    ends = _ends(radio, True)
    assert len(ends) == 2
    assert max(ends) < _sender_deadline(end), [e - _sender_deadline(end) for e in ends]


def test_carrier_running_past_the_bound_on_one_cell_does_not_stop_the_wait_for_another() -> None:
    # Cell 2 carries overlapping transmissions reported as one, longer than any frame; a
    # frame on cell 3 ends well within the bound. The ack went at once and spoilt the
    # frame on cell 3 as well (4x4 at 100 Hz, virtual, seed 0: twice in 10 s).
    radio = Transceiver(random.Random(2))
    end = 20_000
    due = end + SIFS
    radio.carrier(2, 19_000, due + radio.ack_defer + 1)
    radio.carrier(3, 15_000, due + 5_000)
    radio.send_ack(ACK, (1,), end)
    assert radio.advance(due) is None
    assert radio.next_tick == due + 5_000 + SIFS
    assert radio.advance(due + 5_000 + SIFS) == (ACK, (1,))

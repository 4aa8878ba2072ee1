"""The daemon's receive path with two gateways: what one loses, the other makes up."""

from __future__ import annotations

from cellbridge.daemon.core.wire import Ingress
from cellbridge.protocol import ADDR_HOST, Data, Frame, Mode, Sample, encode_stream, fragment


def _datagram(origin: int, seq: int, n: int) -> list[Frame]:
    samples = tuple(Sample(0, 1000 * k, 19_000 + k, 15_000 + k) for k in range(n))
    return fragment(Frame(origin, ADDR_HOST, origin, seq, Data(Mode.COUNTER, samples)), tag=seq % 256, max_frame=64)


def test_a_datagram_whose_head_one_gateway_lost_arrives_once_through_the_other() -> None:
    """Filtering fragments before reassembly lost these: gateway A's tail fragments marked
    the numbers seen, so gateway B's complete copy was dropped as duplicates."""
    ing = Ingress()
    delivered = 0
    for d in range(20):
        frags = _datagram(7, 1 + 16 * d, 12)
        assert len(frags) > 2
        a = b"".join(encode_stream(f) for f in frags[1:])  # gateway A lost the head
        b = b"".join(encode_stream(f) for f in frags)
        for link, data in (("a", a), ("b", b)):
            out = ing.feed(link, data, now=float(d))
            delivered += 0 if out.samples is None else len(out.samples.cycle)
    assert delivered == 20 * 12
    assert ing.duplicates_by_link["a"] == 0


def test_a_readout_same_on_a_serial_line_is_counted_and_ignored_and_takes_no_frame_number() -> None:
    """A READOUT_SAME goes from a bridge to its parent only, numbered from the bridge's link
    numbering (not the host's): one on a serial line (a forged frame, a bridge relaying one
    it could not read, alone, fragmented or bundled) is counted and ignored. Taken through
    the duplicate filter, it marked its (origin, seq) seen, and the bridge's real frame of
    that number was dropped as a duplicate; fed to the loss accounting, its far-off number
    read as the bridge's numbering restarting."""
    from cellbridge.protocol import Bundle, ReadoutSame

    ing = Ingress()
    same = Frame(7, ADDR_HOST, 7, 40, ReadoutSame(3, 12))
    bundled = Frame(2, ADDR_HOST, 2, 900, Bundle((Frame(7, ADDR_HOST, 7, 41, ReadoutSame(3, 12)),)))
    frags = fragment(Frame(7, ADDR_HOST, 7, 42, ReadoutSame(3, 12)), tag=1, max_frame=23)
    out = ing.feed("a", b"".join(encode_stream(f) for f in (same, bundled, *frags)), now=0.0)
    assert 7 not in out.frames_by_origin and out.ignored >= 3
    data = b"".join(encode_stream(f) for f in (_datagram(7, s, 1)[0] for s in (40, 41, 42)))
    out = ing.feed("a", data, now=0.1)
    assert out.samples is not None and len(out.samples.cycle) == 3, "a real frame dropped as a duplicate"
    assert ing.duplicates_by_link["a"] == 0

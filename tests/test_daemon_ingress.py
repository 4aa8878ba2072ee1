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

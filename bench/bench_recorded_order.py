"""What feeding replays in recorded time in one order across links costs, flat out.

Run: ``.venv/bin/python bench/bench_recorded_order.py [--records N]``.

Each link replays a capture of N reads a millisecond apart, the links' reads interleaved
(link i's offset by i/links ms), flat out (``replay_speed = 0``) into a callback that
does nothing: the cost is the links' own, without the pipeline (a read's feed costs about
a millisecond there). "one order" is the service's (:class:`~cellbridge.daemon.shell.links.RecordedOrder`:
a link feeds a read only when no other link's next is older), "each alone" the links
without it, as a replay in shifted time runs. The machine is shared: the figures move
with other load.
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
from pathlib import Path

from cellbridge.daemon.core.config import LinkConfig
from cellbridge.daemon.shell.capture import write_capture
from cellbridge.daemon.shell.links import RecordedOrder, ReplayLink

from timing import table


def run(tmp: Path, links: int, records: int, ordered: bool) -> tuple[float, int]:
    """Seconds to replay every link, and how often recorded time stepped back between reads."""
    names = [f"gw{i}" for i in range(links)]
    for i, name in enumerate(names):
        write_capture(tmp / f"{name}.cbcap", [(1000.0 + 0.001 * (k + i / links), b"x") for k in range(records)])
    order = RecordedOrder(names) if ordered else None
    fed: list[float] = []
    replays = [ReplayLink(LinkConfig(name=n, url=f"replay:{tmp / n}.cbcap", replay_speed=0.0, replay_clock="recorded"),
                          lambda n, d, t: fed.append(t), lambda *a: None, order=order) for n in names]

    async def main() -> None:
        await asyncio.gather(*(r.run() for r in replays))

    t0 = time.perf_counter()
    asyncio.run(main())
    took = time.perf_counter() - t0
    return took, sum(1 for a, b in zip(fed, fed[1:], strict=False) if b < a)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--records", type=int, default=20000, help="reads per link (default: 20000)")
    a = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for links in (1, 2, 4):
            for ordered in (False, True):
                took, back = run(Path(d), links, a.records, ordered)
                n = links * a.records
                rows.append([links, "one order" if ordered else "each alone", n, f"{took:.2f}",
                             f"{took / n * 1e6:.1f}", back])
    table("replays in recorded time, flat out", ["links", "fed", "reads", "s", "us/read", "steps back"], rows)


if __name__ == "__main__":
    main()

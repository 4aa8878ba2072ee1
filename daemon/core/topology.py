"""The mesh as the host sees it: which bridges are alive, their parents, path costs and gateway.

Built from the routing frames bridges send anyway (BEACON: parent and path cost;
STATUS: parent, neighbours and counters) and from which link and which gateway
bridge each bridge's traffic arrives through. Published when its *shape* changes,
so subscribers can redraw the mesh without polling.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any


@dataclass(slots=True)
class Node:
    parent: int | None = None
    path_etx: int | None = None  # tenths of an expected transmission
    hops: int | None = None
    neighbours: dict[int, int] = field(default_factory=dict)  # id -> link ETX (tenths)
    link: str = ""
    gateway: int | None = None  # the bridge holding the serial line this bridge's traffic comes in on
    last_seen: float = 0.0
    queue_drops: int = 0
    retries: int = 0
    resets: int = 0


#: ids -> (those the layout places, the others)
Split = Callable[[Iterable[int]], tuple[list[int], list[int]]]


class Topology:
    def __init__(self) -> None:
        self.nodes: dict[int, Node] = {}
        self.gateways: dict[str, dict[int, float]] = {}  # link -> gateway bridge id -> last heard
        self._published: object = None

    def node(self, bridge: int) -> Node:
        n = self.nodes.get(bridge)
        if n is None:
            n = self.nodes[bridge] = Node()
        return n

    def heard(self, bridge: int, link: str, gateways: set[int], now: float) -> None:
        n = self.node(bridge)
        n.link, n.last_seen = link, now
        if len(gateways) == 1:
            n.gateway = next(iter(gateways))

    def gateways_heard(self, link: str, gateways: set[int], now: float) -> bool:
        """The link-level senders of one read of ``link`` (once per read, not per origin).
        True when one of them is new on ``link`` (it is due to be forgotten some day)."""
        if not gateways:
            return False
        ids = self.gateways.setdefault(link, {})
        if len(gateways) == 1:  # (a line with one gateway: every read of it)
            (gw,) = gateways
            new = gw not in ids
            ids[gw] = now
            return new
        new = not gateways <= ids.keys()
        ids.update(dict.fromkeys(gateways, now))
        return new

    def forget_gateways(self, before: float) -> int:
        """Drop gateway ids last heard on their link ``before``, placed bridges' too: a
        corrupt frame that passes the CRC names a random sender (now and then a placed
        bridge's id), and a bridge that held the line once may no longer; either would
        otherwise be listed as the link's gateway for the life of the daemon. Returns how
        many."""
        n = 0
        for link, ids in list(self.gateways.items()):
            gone = [g for g, t in ids.items() if t < before]
            for g in gone:
                del ids[g]
            n += len(gone)
            if not ids:
                del self.gateways[link]
        return n

    def oldest_gateway(self) -> float:
        """The earliest last-heard time of any gateway id (``inf`` with none)."""
        return min((min(ids.values()) for ids in self.gateways.values() if ids), default=math.inf)

    def clock_stepped_back(self, now: float) -> None:
        for n in self.nodes.values():
            n.last_seen = min(n.last_seen, now)
        for ids in self.gateways.values():
            for g, t in ids.items():
                ids[g] = min(t, now)

    def forget(self, bridge: int) -> None:
        """``bridge`` is forgotten (a phantom or a stranger long silent)."""
        self.nodes.pop(bridge, None)

    def beacon(self, bridge: int, parent: int, path_etx: int, hops: int) -> None:
        n = self.node(bridge)
        n.parent, n.path_etx, n.hops = parent, path_etx, hops

    def status(self, bridge: int, parent: int, path_etx: int, neighbours: dict[int, int],
               queue_drops: int, retries: int, resets: int) -> None:
        n = self.node(bridge)
        n.parent, n.path_etx, n.neighbours = parent, path_etx, neighbours
        n.queue_drops, n.retries, n.resets = queue_drops, retries, resets

    def report(self, now: float, timeout: float, split: Split | None = None,
               shown: int = 0) -> dict[str, Any]:
        """The mesh at ``now``. With ``split`` (ids -> (placed, not placed)), every placed
        bridge (and gateway id) is listed; of the others (phantom origins of a noisy line,
        strangers, bridges not yet placed) only the ``shown`` lowest ids, the rest counted
        in ``bridges_not_shown`` and ``gateways_not_shown``: 65 530 phantoms must not make
        every topology message (and the tick that builds it) megabytes long. Without
        ``split``: every id."""
        ids = self._bounded(self.nodes, split, shown)
        bridges = {}
        for bid in ids:
            n = self.nodes[bid]
            bridges[str(bid)] = {
                "alive": now - n.last_seen <= timeout, "parent": n.parent, "path_etx": n.path_etx,
                "path_cost": None if n.path_etx is None else n.path_etx / 10.0, "hops": n.hops,
                "link": n.link, "gateway": n.gateway, "last_seen": n.last_seen,
                "neighbours": {str(k): v / 10.0 for k, v in sorted(n.neighbours.items())},
            }
        gateways = {k: self._bounded(v, split, shown) for k, v in sorted(self.gateways.items())}
        return {"bridges": bridges, "gateways": gateways,
                "bridges_not_shown": len(self.nodes) - len(ids),
                "gateways_not_shown": sum(len(self.gateways[k]) - len(v) for k, v in gateways.items())}

    @staticmethod
    def _bounded(ids: Iterable[int], split: Split | None, shown: int) -> list[int]:
        """Sorted: every placed id and the ``shown`` lowest of the others."""
        if split is None:
            return sorted(ids)
        keep, others = split(ids)
        return sorted(keep + heapq.nsmallest(shown, others))

    def changed(self, report: dict[str, Any]) -> bool:
        """True once per change of alive set, parents, costs, gateways or links."""
        shape = (
            tuple((k, b["alive"], b["parent"], b["path_etx"], b["link"], b["gateway"])
                  for k, b in report["bridges"].items()),
            tuple((k, tuple(v)) for k, v in report["gateways"].items()),
            report.get("bridges_not_shown", 0), report.get("gateways_not_shown", 0),
        )
        if shape == self._published:
            return False
        self._published = shape
        return True

    def links_of(self, bridge: int) -> list[str]:
        n = self.nodes.get(bridge)
        return [n.link] if n is not None and n.link else []

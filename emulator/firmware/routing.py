"""CTP-style collection routing: Trickle beacons, ETX path cost, parent hysteresis.

Each bridge keeps a small neighbour table filled from beacons (the neighbour's
parent, path cost and hops) and from its own link-layer results (attempts per
delivered frame give the link's ETX). Its path cost is the best neighbour's path
cost plus the link to it; it changes parent only when another one is better by
``hysteresis``, so routes do not flap on noise. Loops are avoided three ways: a
neighbour whose beacon names us as its parent, or that just sent us a frame to
forward, is never chosen (two-bridge loops),
a frame that arrives from a neighbour that advertises a cost no higher than ours
is an inconsistency that resets the beacon timer so the stale cost is corrected
fast, a frame that comes back with more hops than it had (the same origin and sequence
number: it went round a loop through us) makes us drop our parent and choose again,
and frames that travelled more than ``max_hops`` are dropped (counted).
"""

from __future__ import annotations

import random
from dataclasses import dataclass

INFINITE = 0xFFFF  #: path cost of a bridge with no route
PERFECT_LINK = 10  #: one expected transmission, in tenths


class Trickle:
    """Trickle timer (RFC 6206): beacon often after a change, rarely when all agree."""

    def __init__(self, rng: random.Random, imin: int, imax: int, k: int = 3) -> None:
        self._rng = rng
        self.imin, self.imax, self.k = imin, imax, k
        self.interval = imin
        self.counter = 0
        self.fire_at = 0
        self.end_at = 0

    def start(self, tick: int) -> None:
        self.interval = self.imin
        self._new_interval(tick)

    def _new_interval(self, tick: int) -> None:
        self.counter = 0
        self.end_at = tick + self.interval
        self.fire_at = tick + self.interval // 2 + self._rng.randrange(max(1, self.interval // 2))

    def reset(self, tick: int) -> None:
        """An inconsistency: go back to the shortest interval (no-op if already there)."""
        if self.interval != self.imin or self.fire_at < tick:
            self.interval = self.imin
            self._new_interval(tick)

    def heard_consistent(self) -> None:
        self.counter += 1

    @property
    def next_tick(self) -> int:
        f = self.fire_at
        return f if 0 <= f < self.end_at else self.end_at

    def advance(self, tick: int, force: bool = False) -> bool:
        """True when a beacon should be sent now (``force``: whatever was heard)."""
        fire = False
        if 0 <= self.fire_at <= tick:
            fire = force or self.counter < self.k
            self.fire_at = -1
        if self.end_at <= tick:
            self.interval = min(self.interval * 2, self.imax)
            self._new_interval(tick)
        return fire


@dataclass
class Neighbour:
    id: int
    parent: int = 0
    path_etx: int = INFINITE
    hops: int = 0
    link_etx: float = float(PERFECT_LINK)
    heard: int = 0
    failures: int = 0  #: consecutive frames not acknowledged after all retries


class Router:
    """Parent choice of one bridge. A gateway is the root: cost 0, no parent."""

    def __init__(self, me: int, gateway: bool, hysteresis: int = 15, max_failures: int = 2,
                 neighbour_timeout: int = 150_000_000, max_hops: int = 32,
                 max_neighbours: int = 32) -> None:
        self.me = me
        self.gateway = gateway
        self.hysteresis = hysteresis
        self.max_failures = max_failures
        self.neighbour_timeout = neighbour_timeout
        self.max_hops = max_hops
        self.max_neighbours = max_neighbours
        self.table: dict[int, Neighbour] = {}
        self.parent: int | None = None
        self.path_etx = 0 if gateway else INFINITE
        self.hops = 0
        self.parent_changes = 0
        #: neighbours dropped, in all and by cause: frames to it failed ``max_failures``
        #: times in a row, it was silent ``neighbour_timeout``, or it routed through us
        self.evictions = 0
        self.evictions_failed = 0
        self.evictions_silent = 0
        self.evictions_loop = 0

    @property
    def has_route(self) -> bool:
        return self.gateway or self.parent is not None

    def _cost_via(self, n: Neighbour) -> int:
        if n.path_etx >= INFINITE or n.parent == self.me or n.hops >= self.max_hops:
            return INFINITE
        return min(INFINITE, n.path_etx + int(round(n.link_etx)))

    def on_beacon(self, src: int, parent: int, path_etx: int, hops: int, tick: int) -> None:
        n = self.table.get(src)
        if n is None:
            if len(self.table) >= self.max_neighbours:
                worst = max(self.table.values(), key=self._cost_via)
                if self._cost_via(worst) <= path_etx:
                    return
                del self.table[worst.id]
            n = self.table[src] = Neighbour(src)
        n.parent, n.path_etx, n.hops, n.heard = parent, path_etx, hops, tick

    def on_link_result(self, nbr: int, attempts: int, ok: bool, tick: int | None = None) -> None:
        """Feed the outcome of one frame sent to ``nbr`` (``attempts`` transmissions) at
        ``tick``. An acknowledged frame proves the neighbour alive as a beacon does: a
        parent that Trickle keeps quiet is not expired while it acknowledges our frames."""
        n = self.table.get(nbr)
        if n is None:
            return
        sample = attempts * PERFECT_LINK if ok else (attempts + 2) * PERFECT_LINK
        n.link_etx = 0.8 * n.link_etx + 0.2 * sample
        if ok:
            n.failures = 0
            if tick is not None:
                n.heard = max(n.heard, tick)
        else:
            n.failures += 1
            if n.failures >= self.max_failures:
                del self.table[nbr]
                self.evictions += 1
                self.evictions_failed += 1

    def expire(self, tick: int) -> None:
        for nid in [nid for nid, n in self.table.items() if tick - n.heard > self.neighbour_timeout]:
            del self.table[nid]
            self.evictions += 1
            self.evictions_silent += 1

    def select(self) -> bool:
        """Re-choose the parent; True when the route changed in a way beacons must tell."""
        if self.gateway:
            return False
        old_parent, old_cost = self.parent, self.path_etx
        best, best_cost = None, INFINITE
        for n in self.table.values():
            c = self._cost_via(n)
            if c < best_cost or (c == best_cost and best is not None and n.id < best.id):
                best, best_cost = n, c
        cur = self.table.get(self.parent) if self.parent is not None else None
        cur_cost = self._cost_via(cur) if cur is not None else INFINITE
        if cur is not None and cur_cost < INFINITE and best_cost + self.hysteresis >= cur_cost:
            best, best_cost = cur, cur_cost
        if best is None or best_cost >= INFINITE:
            self.parent, self.path_etx, self.hops = None, INFINITE, 0
        else:
            self.parent, self.path_etx, self.hops = best.id, best_cost, best.hops + 1
        if self.parent != old_parent:
            self.parent_changes += 1
            return True
        return abs(self.path_etx - old_cost) > self.hysteresis

    def loop_detected(self) -> None:
        """A frame came back with more hops: our parent's route leads through us. Drop
        the parent until it is heard again (with fresh costs) and choose again."""
        if self.parent is not None and self.parent in self.table:
            del self.table[self.parent]
            self.evictions += 1
            self.evictions_loop += 1

    def child_sent(self, sender: int) -> bool:
        """``sender`` forwarded a frame to us, so its parent is us (datapath validation).
        True when it was our parent: a two-bridge loop, now broken by choosing again."""
        n = self.table.get(sender)
        if n is not None:
            n.parent = self.me
        if sender == self.parent:
            self.select()
            return True
        return False

    def inconsistent(self, sender: int) -> bool:
        """A frame to forward came from ``sender``: is its advertised cost no higher than ours?"""
        n = self.table.get(sender)
        return n is not None and n.path_etx <= self.path_etx and not self.gateway

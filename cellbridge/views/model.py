"""The skin view model: what the daemon's messages say, as something to draw.

Sans-I/O: fed decoded payloads of the daemon's PUB topics (``element``, ``contact``,
``health``, ``topology``, see ``docs/zmq-api.md``) with the receiver's monotonic time,
it keeps the newest reading of every element, the tracked contacts, a summary of the
mesh's health, and this subscriber's own losses; :meth:`SkinView.frame` turns that into
a :class:`Frame` (grid cells with a colour level and a label, contacts in grid units,
status lines) that the terminal view, the web page and the Foxglove bridge all draw.

Fields are read defensively: a payload may carry keys this model does not know (the
schema grows by adding), lack optional ones, or hold a wrong type; nothing here raises
on a payload, a bad one is counted in ``malformed`` instead.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

TOPICS = ("element", "contact", "health", "topology")
STALE_AFTER = 3.0  # s without any message: the daemon is shown as gone
HISTORY = 1000  # samples of each element kept for plots (10 s at 100 Hz)
UNTOUCHED = 2  # element status bit: below the noise floor


def _num(value: Any) -> float:
    """A float from a msgpack value; NaN for anything that is not a number."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return math.nan
    return float(value)


def _col(payload: dict[str, Any], key: str, n: int) -> list[Any]:
    """Column ``key`` of a columnar payload, padded with None to ``n`` entries."""
    col = payload.get(key)
    if not isinstance(col, list):
        return [None] * n
    return col[:n] + [None] * (n - len(col))


@dataclass
class Element:
    """The newest reading of one element (bridge)."""

    bridge: int
    force: float = math.nan
    area: float = math.nan
    dc1: float = math.nan
    dc2: float = math.nan
    valid: bool = False
    touched: bool = False
    status: int = 0
    t_sample: float = math.nan
    history: deque[tuple[float, float, float]] = field(default_factory=lambda: deque(maxlen=HISTORY))

    def shown_force(self) -> float:
        """Force to colour by: the inverse's force, 0 for an untouched element, NaN when unknown."""
        if self.valid and math.isfinite(self.force):
            return self.force
        if self.status & UNTOUCHED and not self.touched:
            return 0.0
        return math.nan


@dataclass
class Contact:
    id: int
    x: float
    y: float
    force: float
    diameter: float
    observable: tuple[bool, bool] = (True, True)
    valid: bool = True
    missed: int = 0
    sigma_x: float = math.nan
    sigma_y: float = math.nan
    elements: tuple[int, ...] = ()


@dataclass
class Cell:
    """One element as drawn: where on the grid, how strong a colour, which label."""

    bridge: int
    row: int
    col: int
    level: float  # 0..1 colour level; NaN: no reading (drawn grey)
    label: str  # short: "2.0N", "1.3pF", "" (untouched), "?" (unknown)
    touched: bool
    force: float
    dc1: float
    quantity: str = "force"  # what level and label show: "force" (N), "dc" (ΔC1, pF) or "none"


@dataclass
class DrawnContact:
    id: int
    col: float  # grid units: 0 is the left edge of column 0
    row: float
    diameter: float  # grid units
    level: float
    force: float
    x: float
    y: float
    diameter_m: float
    observable: tuple[bool, bool]
    valid: bool
    label: str  # "#3 2.00 N"
    line: str  # one full text line for a list


@dataclass
class Frame:
    rows: int
    cols: int
    side: float
    origin: tuple[float, float]  # (x, y) of the grid's corner, m
    quantity: str  # "force" when some element shows a force, else "dc" (cells say their own)
    scale: float  # value at colour level 1 (N or pF) of ``quantity``
    cells: list[Cell]
    contacts: list[DrawnContact]
    status: list[str]
    live: bool
    paused: bool
    counters: dict[str, Any]


def level_rgb(level: float) -> tuple[int, int, int]:
    """The colour of a level 0..1 (dark blue, through teal and yellow, to red); grey for NaN.

    One ramp for every view, so a force looks the same in the terminal, the page and Foxglove."""
    if not math.isfinite(level):
        return (90, 90, 90)
    stops = ((0.0, (20, 24, 60)), (0.25, (20, 110, 150)), (0.6, (240, 200, 40)), (1.0, (220, 30, 30)))
    level = min(1.0, max(0.0, level))
    for (a, ca), (b, cb) in zip(stops, stops[1:]):
        if level <= b:
            t = (level - a) / (b - a)
            return tuple(int(round(u + (v - u) * t)) for u, v in zip(ca, cb))  # type: ignore[return-value]  # three channels in, three out
    return stops[-1][1]


def format_force(f: float) -> str:
    return "?" if not math.isfinite(f) else f"{f:.2f} N"


def format_mm(v: float) -> str:
    return "?" if not math.isfinite(v) else f"{v * 1e3:.1f} mm"


def contact_line(c: Contact) -> str:
    """One contact as a line of text: id, position (unresolved axes as such), force, diameter."""
    def axis(name: str, v: float, ok: bool, sigma: float) -> str:
        if ok:
            return f"{name} {format_mm(v)}"
        s = f" ±{sigma * 1e3:.0f}" if math.isfinite(sigma) else ""
        return f"{name} ~{v * 1e3:.1f}{s} mm (unresolved)"
    parts = [f"#{c.id}", axis("x", c.x, c.observable[0], c.sigma_x), axis("y", c.y, c.observable[1], c.sigma_y),
             f"F {format_force(c.force)}", f"⌀ {format_mm(c.diameter)}"]
    if not c.valid:
        parts.append("(no pressure: position only)")
    if c.missed:
        parts.append(f"(missed {c.missed})")
    return "  ".join(parts)


class SkinView:
    """The view model: feed it messages, ask it for a :class:`Frame`.

    ``force_scale`` is the force (N) drawn at full colour; ``dc_scale`` the ΔC1 (pF)
    drawn at full colour while elements have no force (calibration not finished, or
    outside the inverse's valid region).
    """

    def __init__(self, force_scale: float = 5.0, dc_scale: float = 2.0, stale_after: float = STALE_AFTER) -> None:
        self.force_scale = force_scale  # N at full colour
        self.dc_scale = dc_scale  # pF at full colour
        self.stale_after = stale_after
        self.elements: dict[int, Element] = {}
        self.layout: dict[int, tuple[float, float]] = {}
        self.side = 0.04
        self.contacts: list[Contact] = []
        self.contact_t: float = math.nan
        self.health: dict[str, Any] = {}
        self.health_summary: dict[str, Any] = {}
        self.received: dict[str, int] = {}
        self.lost: dict[str, int] = {}  # messages this subscriber missed (seq gaps), per topic
        self.malformed = 0
        self.daemon_restarts = 0
        self.last_seq: dict[str, int] = {}
        self.last_message: float = -math.inf
        self.changed = True
        self.paused = False
        self._uptime = -math.inf
        self.needs_topology = True  # the shell asks the control socket for the layout while set

    # ---- input --------------------------------------------------------------------

    def feed(self, topic: str, payload: Any, now: float) -> None:
        """One message from the PUB socket, decoded; ``now`` is the receiver's monotonic time."""
        self.last_message = now
        self.received[topic] = self.received.get(topic, 0) + 1
        if not isinstance(payload, dict):
            self.malformed += 1
            return
        self._count_seq(topic, payload)
        try:
            if topic == "element":
                self._feed_element(payload)
            elif topic == "contact":
                self._feed_contact(payload)
            elif topic == "health":
                self._feed_health(payload)
            elif topic == "topology":
                self.feed_topology(payload)
        except (TypeError, ValueError, KeyError, AttributeError):
            self.malformed += 1
            return
        self.changed = True

    def feed_malformed(self, now: float) -> None:
        """A message that was not [topic, msgpack payload]: counted, never dropped silently."""
        self.last_message = now
        self.malformed += 1

    def _count_seq(self, topic: str, payload: dict[str, Any]) -> None:
        seq = payload.get("seq")
        if not isinstance(seq, int) or isinstance(seq, bool):
            return
        last = self.last_seq.get(topic)
        self.last_seq[topic] = seq
        if last is None:
            return
        if seq <= last:  # numbering started again: a new daemon process
            if topic == "health":
                self.daemon_restarts += 1
                self.needs_topology = True
            return
        if seq > last + 1:
            self.lost[topic] = self.lost.get(topic, 0) + seq - last - 1

    def feed_topology(self, payload: dict[str, Any]) -> None:
        """A ``topology`` message or the reply of the control request ``topology``."""
        layout = payload.get("layout")
        if not isinstance(layout, dict):
            return
        ids, xs, ys = layout.get("ids"), layout.get("x"), layout.get("y")
        if not (isinstance(ids, list) and isinstance(xs, list) and isinstance(ys, list)):
            return
        side = _num(layout.get("side"))
        if math.isfinite(side) and side > 0:
            self.side = side
        self.layout = {int(b): (_num(x), _num(y)) for b, x, y in zip(ids, xs, ys)
                       if isinstance(b, int) and math.isfinite(_num(x)) and math.isfinite(_num(y))}
        self.needs_topology = not self.layout
        self.changed = True

    def _feed_element(self, p: dict[str, Any]) -> None:
        bridges = p.get("bridge")
        if not isinstance(bridges, list):
            raise ValueError("element without bridge column")
        n = len(bridges)
        cols = [_col(p, k, n) for k in ("force", "area", "dc1", "dc2", "valid", "touched", "status", "t_sample")]
        for b, force, area, dc1, dc2, valid, touched, status, ts in zip(bridges, *cols):
            if not isinstance(b, int):
                continue
            e = self.elements.get(b)
            if e is None:
                e = self.elements[b] = Element(b)
                if b not in self.layout:
                    self.needs_topology = True
            e.force, e.area, e.dc1, e.dc2 = _num(force), _num(area), _num(dc1), _num(dc2)
            e.valid, e.touched = valid is True, touched is True
            e.status = status if isinstance(status, int) else 0
            e.t_sample = _num(ts)
            e.history.append((e.t_sample, e.shown_force(), e.dc1))

    def _feed_contact(self, p: dict[str, Any]) -> None:
        contacts = p.get("contacts")
        if not isinstance(contacts, list):
            raise ValueError("contact without contacts")
        out = []
        for c in contacts:
            if not isinstance(c, dict) or not isinstance(c.get("id"), int):
                self.malformed += 1
                continue
            obs = c.get("observable")
            observable = (obs[0] is not False, obs[1] is not False) if isinstance(obs, list) and len(obs) >= 2 \
                else (True, True)
            elements = c.get("elements")
            out.append(Contact(id=c["id"], x=_num(c.get("x")), y=_num(c.get("y")), force=_num(c.get("force")),
                               diameter=_num(c.get("diameter")), observable=observable,
                               valid=c.get("valid") is not False,
                               missed=c["missed"] if isinstance(c.get("missed"), int) else 0,
                               sigma_x=_num(c.get("sigma_x")), sigma_y=_num(c.get("sigma_y")),
                               elements=tuple(e for e in elements if isinstance(e, int))
                               if isinstance(elements, list) else ()))
        self.contacts = out
        self.contact_t = _num(p.get("t_sample"))

    def _feed_health(self, p: dict[str, Any]) -> None:
        uptime = _num(p.get("uptime"))
        self._uptime = uptime
        self.health = p
        self.health_summary = summarise_health(p)

    # ---- output -------------------------------------------------------------------

    def live(self, now: float) -> bool:
        return now - self.last_message <= self.stale_after

    def frame(self, now: float) -> Frame:
        """What to draw now. Clears :attr:`changed`."""
        self.changed = False
        placed = {b: xy for b, xy in self.layout.items()}
        for b in self.elements:  # a bridge without a known position still shows, after the placed ones
            placed.setdefault(b, (math.nan, math.nan))
        side = self.side
        finite = [xy for xy in placed.values() if math.isfinite(xy[0])]
        x0 = min((x for x, _ in finite), default=0.0) - side / 2
        y0 = min((y for _, y in finite), default=0.0) - side / 2
        cells: list[Cell] = []
        rows = cols = 0
        unplaced = sorted(b for b, xy in placed.items() if not math.isfinite(xy[0]))
        for b, (x, y) in sorted(placed.items()):
            if not math.isfinite(x):
                continue
            col, row = int(round((x - x0) / side - 0.5)), int(round((y - y0) / side - 0.5))
            cells.append(self._cell(b, row, col))
            rows, cols = max(rows, row + 1), max(cols, col + 1)
        for i, b in enumerate(unplaced):  # an extra row below the skin
            cells.append(self._cell(b, rows, i))
        if unplaced:
            cols = max(cols, len(unplaced))
            rows += 1
        quantity = "force" if not cells or any(c.quantity == "force" for c in cells) else "dc"
        drawn = []
        for c in self.contacts:
            d = c.diameter if math.isfinite(c.diameter) else 0.0
            level = min(1.0, max(0.0, c.force / self.force_scale)) if math.isfinite(c.force) else math.nan
            drawn.append(DrawnContact(
                id=c.id, col=(c.x - x0) / side, row=(c.y - y0) / side, diameter=d / side, level=level,
                force=c.force, x=c.x, y=c.y, diameter_m=c.diameter, observable=c.observable, valid=c.valid,
                label=f"#{c.id} {format_force(c.force)}", line=contact_line(c)))
        return Frame(rows=rows, cols=cols, side=side, origin=(x0, y0), quantity=quantity,
                     scale=self.force_scale if quantity == "force" else self.dc_scale, cells=cells,
                     contacts=drawn, status=self.status_lines(now), live=self.live(now), paused=self.paused,
                     counters=self.counters())

    def _cell(self, bridge: int, row: int, col: int) -> Cell:
        """An element's force where the inverse gives one (0 when untouched); else its ΔC1
        (a light, ambiguous touch); else grey: "cal" while its baseline is taken, "?"."""
        e = self.elements.get(bridge)
        if e is None:
            return Cell(bridge, row, col, math.nan, "·", False, math.nan, math.nan)
        f = e.shown_force()
        if math.isfinite(f):
            return Cell(bridge, row, col, min(1.0, max(0.0, f / self.force_scale)), f"{f:.1f}N" if f > 0 else "",
                        e.touched, f, e.dc1)
        dc = e.dc1 * 1e12
        if math.isfinite(dc):
            return Cell(bridge, row, col, min(1.0, max(0.0, dc / self.dc_scale)), f"{dc:.1f}pF", e.touched, f, e.dc1,
                        quantity="dc")
        return Cell(bridge, row, col, math.nan, "cal" if e.status & 1 else "?", e.touched, f, e.dc1, quantity="none")

    def counters(self) -> dict[str, Any]:
        return {"received": dict(self.received), "lost": dict(self.lost), "malformed": self.malformed,
                "daemon_restarts": self.daemon_restarts}

    def status_lines(self, now: float) -> list[str]:
        """The status area: daemon, links, bridges, loss, rate, estimation time, this view's losses."""
        h = self.health_summary
        lines = []
        if self.last_message == -math.inf:
            lines.append("daemon: waiting for the first message")
        elif not self.live(now):
            lines.append(f"daemon: SILENT for {now - self.last_message:.0f} s (stopped? reconnecting by itself)")
        else:
            lines.append(f"daemon: live  uptime {h.get('uptime', math.nan):.0f} s"
                         + (f"  restarts seen {self.daemon_restarts}" if self.daemon_restarts else ""))
        if h:
            lines.append(f"links: {h['links_up']}/{h['links']} up  {h['link_text']}")
            lines.append(f"bridges: {h['alive']} alive, {h['silent']} silent  loss {h['loss'] * 100:.2f} %  "
                         f"rate {h['rate']:.0f} samples/s")
            lines.append(f"contacts: estimate {h['est_ms']:.2f} ms (max {h['est_max_ms']:.2f})  "
                         f"calibration {h['calibration']}")
        lost = sum(self.lost.values())
        lines.append(f"this view: {sum(self.received.values())} messages, lost {lost}"
                     + (f"  (daemon dropped {h['pub_dropped']})" if h.get("pub_dropped") else "")
                     + (f" ({', '.join(f'{k} {v}' for k, v in sorted(self.lost.items()))})" if lost else "")
                     + (f", malformed {self.malformed}" if self.malformed else "")
                     + ("  [PAUSED]" if self.paused else ""))
        return lines


def _table(p: dict[str, Any], key: str) -> dict[Any, Any]:
    """``p[key]`` when it is a map, else an empty one."""
    v = p.get(key)
    return v if isinstance(v, dict) else {}


def summarise_health(p: dict[str, Any]) -> dict[str, Any]:
    """The few figures of a ``health`` payload a status area shows (defensive: any may be absent)."""
    links = _table(p, "links")
    bridges = _table(p, "bridges")
    up = [n for n, ln in links.items() if isinstance(ln, dict) and ln.get("connected")]
    silent = [b for b, br in bridges.items() if isinstance(br, dict) and br.get("silent")]
    lost = sum(_num(br.get("lost")) for br in bridges.values() if isinstance(br, dict) and math.isfinite(_num(br.get("lost"))))
    frames = sum(_num(br.get("frames")) for br in bridges.values() if isinstance(br, dict) and math.isfinite(_num(br.get("frames"))))
    rate = sum(_num(br.get("sample_rate")) for br in bridges.values()
               if isinstance(br, dict) and math.isfinite(_num(br.get("sample_rate"))))
    est = _table(p, "contact_estimation")
    cal = _table(_table(p, "layout"), "calibration")
    dropped = _table(_table(p, "pub"), "dropped")
    link_text = "  ".join(f"{n}:{'up' if n in up else 'DOWN'}" for n in sorted(links)[:4])
    return {
        "uptime": _num(p.get("uptime")),
        "links": len(links), "links_up": len(up), "link_text": link_text,
        "alive": len(bridges) - len(silent), "silent": len(silent),
        "loss": lost / (lost + frames) if lost + frames > 0 else 0.0,
        "rate": rate,
        "est_ms": _num(est.get("last_ms")), "est_max_ms": _num(est.get("max_ms")),
        "calibration": (f"{cal.get('ready', '?')} ready, {cal.get('collecting', 0)} collecting"
                        if cal else "?"),
        "pub_dropped": int(sum(v for v in dropped.values() if isinstance(v, (int, float)))),
    }

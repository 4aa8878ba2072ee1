"""The skin view model: what the daemon's messages say, as something to draw.

Sans-I/O: fed decoded payloads of the daemon's PUB topics (``element``, ``contact``,
``health``, ``topology``, see ``docs/zmq-api.md``) with the receiver's monotonic time,
it keeps the newest reading of every element, the tracked contacts, a summary of the
mesh's health, and this subscriber's own losses; :meth:`SkinView.frame` turns that into
a :class:`Frame` (grid cells with a colour level and a label, contacts in grid units,
status lines) that the terminal view, the web page and the Foxglove bridge all draw.
With a skin on a robot (``topology``'s ``skin``, read by
:mod:`cellbridge.views.robot_skin`) the frame is patch by patch: each patch's elements
on a block of their own (:attr:`Frame.patches`), the contacts on their patch's block;
the contacts keep their link, patch, position, normal and force vector for Foxglove.

Fields are read defensively: a payload may carry keys this model does not know (the
schema grows by adding), lack optional ones, or hold a wrong type; nothing here raises
on a payload, a bad one is counted in ``malformed`` instead. What is kept is bounded
whatever the payloads say: at most :data:`MAX_ELEMENTS` elements and
:data:`MAX_CONTACTS` contacts, a grid of at most :data:`MAX_GRID` cells a side (a layout
that would need more is drawn as a list of unplaced elements, and the status says so),
positions within :data:`MAX_COORD` of the origin, and a bounded copy of ``health``.
Every string from the daemon that reaches a status line passes :func:`printable`:
control characters are shown escaped (``\\x1b``), never written to a terminal.

One picture shows one daemon: every payload names its daemon (``source``); a view
shows the source it was given (``--source``) or else the first one it hears, and counts
the messages of any other (several daemons behind one ``cellbridge proxy``) without
drawing them.
"""

from __future__ import annotations

import math
import unicodedata
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from cellbridge.views.robot_skin import PatchBlock, RobotSkin, pack_patches, read_skin, unit3, vec3

TOPICS = ("element", "contact", "health", "topology")
STALE_AFTER = 3.0  # s without any message: the daemon is shown as gone
HISTORY = 1000  # samples of each element kept for plots (10 s at 100 Hz)
UNTOUCHED = 2  # element status bit: below the noise floor
MAX_ELEMENTS = 4096  #: elements kept (a 64×64 skin); readings of any further bridge id are counted, not kept
MAX_CONTACTS = 64  #: contacts kept of one ``contact`` message; the rest are counted
MAX_GRID = 128  #: most grid cells a side the layout is drawn on (5.1 m of 40 mm elements)
UNPLACED_PER_ROW = 16  #: elements without a position are drawn in rows of at least this many
MAX_COORD = 1e3  #: m: a position further from the origin is taken as unknown
MAX_SIDE = 10.0  #: m: a larger element side is taken as unknown (the last good one stays)
MAX_BRIDGE = 0xFFFF  #: bridge ids are 16-bit
MAX_COLUMN = 65536  #: entries of one columnar message read (a real read holds far fewer)
HISTORY_BUDGET = 256 * HISTORY  #: samples kept for plots over all elements (each at most HISTORY)
MAX_OTHER_SOURCES = 8  #: names of other sources remembered (the rest only counted)
SHOWN_TEXT = 60  #: characters of a daemon's string shown in a status line


def _num(value: Any) -> float:
    """A float from a msgpack value; NaN for anything that is not a number."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return math.nan
    return float(value)


def _pos(value: Any) -> float:
    """A position (m) from a msgpack value; NaN unless a number within :data:`MAX_COORD`."""
    v = _num(value)
    return v if -MAX_COORD <= v <= MAX_COORD else math.nan


def _size(value: Any) -> float:
    """A size or spread (m); NaN unless a number in [0, :data:`MAX_COORD`]."""
    v = _num(value)
    return v if 0.0 <= v <= MAX_COORD else math.nan


def _label(value: Any) -> str | None:
    """A name from the daemon (a link's, a patch's), at most 64 characters; None if not a string."""
    return value[:64] if isinstance(value, str) else None


def _force3(value: Any) -> tuple[float, float, float] | None:
    """A force vector (N): three finite numbers, each within ±1e6."""
    return vec3(value, 1e6)


def _bridge(value: Any) -> int | None:
    """A bridge id (16-bit), or None."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_BRIDGE:
        return None
    return value


def _col(payload: dict[str, Any], key: str, n: int) -> list[Any]:
    """Column ``key`` of a columnar payload, padded with None to ``n`` entries."""
    col = payload.get(key)
    if not isinstance(col, list):
        return [None] * n
    return col[:n] + [None] * (n - len(col))


_SHOWN_AS_IS = {"Cc", "Cf", "Cs", "Zl", "Zp"}  # categories escaped: controls, formats (bidi), separators


def printable(text: Any, limit: int = SHOWN_TEXT) -> str:
    """``text`` safe to show anywhere, a terminal too: control and format characters (C0,
    DEL, C1, bidi overrides, line separators) as Python escapes (``\\x1b``,
    ``\\u202e``), at most ``limit`` characters (cut with ``…``). A value that is not a
    string shows as its type's name in angle brackets."""
    if not isinstance(text, str):
        text = f"<{type(text).__name__}>"
    out = []
    n = 0
    for ch in text:
        if unicodedata.category(ch) in _SHOWN_AS_IS:
            o = ord(ch)
            ch = f"\\x{o:02x}" if o < 0x100 else f"\\u{o:04x}" if o < 0x10000 else f"\\U{o:08x}"
        n += len(ch)
        if n > limit:
            out.append("…")
            break
        out.append(ch)
    return "".join(out)


def fmt(v: float, spec: str = ".1f") -> str:
    """A number for a label or a status line: ``spec``, but a huge one in three digits
    (``1e+308``, not 309 of them) and ``?`` for NaN."""
    if math.isnan(v):
        return "?"
    if math.isinf(v) or abs(v) >= 1e6:
        return f"{v:.3g}"
    return format(v, spec)


def bounded(value: Any, budget: int = 100_000, depth: int = 12) -> Any:
    """A copy of a msgpack value holding at most ``budget`` items (beyond it containers are
    cut, with a ``"…"`` entry saying how many were left out) and ``depth`` levels (deeper:
    ``"…"``), strings at most 1000 characters: what a view keeps of a payload it passes on
    (Foxglove's health channel), whatever its size."""
    left = [budget]

    def copy(v: Any, d: int) -> Any:
        left[0] -= 1
        if isinstance(v, str):
            return v if len(v) <= 1000 else v[:1000] + "…"
        if isinstance(v, (bytes, bytearray)):
            return bytes(v[:1000])
        if isinstance(v, dict):
            if d <= 0:
                return "…"
            out: dict[Any, Any] = {}
            for i, (k, x) in enumerate(v.items()):
                if left[0] <= 0:
                    out["…"] = f"{len(v) - i} more"
                    break
                out[copy(k, 0) if isinstance(k, (str, bytes)) else k] = copy(x, d - 1)
            return out
        if isinstance(v, (list, tuple)):
            if d <= 0:
                return "…"
            items = []
            for i, x in enumerate(v):
                if left[0] <= 0:
                    items.append(f"… {len(v) - i} more")
                    break
                items.append(copy(x, d - 1))
            return items
        return v if v is None or isinstance(v, (bool, int, float)) else f"<{type(v).__name__}>"

    return copy(value, depth)


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
    # on the robot (None: not said, or unreadable): the link and patch, the centre and the
    # skin's outward normal in the link frame (m), the force vector (N)
    link: str | None = None
    patch: str | None = None
    position: tuple[float, float, float] | None = None
    normal: tuple[float, float, float] | None = None
    force_vector: tuple[float, float, float] | None = None


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
    patches: list[PatchBlock] = field(default_factory=list)  # with a skin on a robot: each patch's block


def _ramp(level: float) -> tuple[int, int, int]:
    stops = ((0.0, (20, 24, 60)), (0.25, (20, 110, 150)), (0.6, (240, 200, 40)), (1.0, (220, 30, 30)))
    for (a, ca), (b, cb) in zip(stops, stops[1:]):
        if level <= b:
            t = (level - a) / (b - a)
            return tuple(int(round(u + (v - u) * t)) for u, v in zip(ca, cb))  # type: ignore[return-value]  # three channels in, three out
    return stops[-1][1]


_RAMP = [_ramp(i / 4096) for i in range(4097)]  # the ramp in 4096 steps (a colour step is ~1/20 of that)


def level_rgb(level: float) -> tuple[int, int, int]:
    """The colour of a level 0..1 (dark blue, through teal and yellow, to red); grey for NaN.

    One ramp for every view, so a force looks the same in the terminal, the page and Foxglove."""
    if not math.isfinite(level):
        return (90, 90, 90)
    return _RAMP[round(min(1.0, max(0.0, level)) * 4096)]


def format_force(f: float) -> str:
    return "?" if not math.isfinite(f) else f"{fmt(f, '.2f')} N"


def format_mm(v: float) -> str:
    return "?" if not math.isfinite(v) else f"{fmt(v * 1e3)} mm"


def contact_line(c: Contact) -> str:
    """One contact as a line of text: id, position (unresolved axes as such), force, diameter."""
    def axis(name: str, v: float, ok: bool, sigma: float) -> str:
        if ok:
            return f"{name} {format_mm(v)}"
        s = f" ±{fmt(sigma * 1e3, '.0f')}" if math.isfinite(sigma) else ""
        return f"{name} ~{fmt(v * 1e3)}{s} mm (unresolved)"
    parts = [f"#{c.id}", axis("x", c.x, c.observable[0], c.sigma_x), axis("y", c.y, c.observable[1], c.sigma_y),
             f"F {format_force(c.force)}", f"⌀ {format_mm(c.diameter)}"]
    if c.link is not None or c.patch is not None:  # on a robot: where on it (x, y are on the unrolled skin)
        parts.insert(1, f"on {printable(c.link or '?', 20)}/{printable(c.patch or '?', 20)}")
        if all(c.observable):
            at = "(" + ", ".join(fmt(v * 1e3) for v in c.position) + ") mm" if c.position is not None else "?"
            parts[2:4] = [f"at {at}"]
    if not c.valid:
        parts.append("(no pressure: position only)")
    if c.missed:
        parts.append(f"(missed {c.missed})")
    return "  ".join(parts)



class SkinView:
    """The view model: feed it messages, ask it for a :class:`Frame`.

    ``force_scale`` is the force (N) drawn at full colour; ``dc_scale`` the ΔC1 (pF)
    drawn at full colour while elements have no force (calibration not finished, or
    outside the inverse's valid region). ``source`` is the daemon shown (a payload's
    ``source``); None: the first one heard. Messages of any other source are counted
    (:attr:`other_sources`) and otherwise ignored: one picture never mixes two skins.
    """

    def __init__(self, force_scale: float = 5.0, dc_scale: float = 2.0, stale_after: float = STALE_AFTER,
                 source: str | None = None, endpoint: str | None = None, quiet_after: float = math.inf) -> None:
        self.endpoint = endpoint  # the daemon's PUB endpoint, named when nothing comes from it
        self.quiet_after = quiet_after  # s with no message at all before the status says no daemon answers
        self._waiting_since: float | None = None  # when the status was first asked for
        self.force_scale = force_scale  # N at full colour
        self.dc_scale = dc_scale  # pF at full colour
        self.stale_after = stale_after
        self.source = source
        self.source_given = source is not None
        self.other_sources: dict[str, int] = {}  # messages of each other source heard (names: the first few)
        self.other_sources_more = 0  # messages of other sources beyond those names
        self.elements: dict[int, Element] = {}
        self.layout: dict[int, tuple[float, float]] = {}
        self.side = 0.04
        self.contacts: list[Contact] = []
        self.contact_t: float = math.nan
        self.health: dict[str, Any] = {}  # the newest health payload, a bounded copy
        self.health_summary: dict[str, Any] = {}
        self.health_count = 0  # health messages taken from the shown source
        self.received: dict[str, int] = {}
        self.lost: dict[str, int] = {}  # messages this subscriber missed (seq gaps), per topic
        self.malformed = 0
        self.unknown_topics = 0  # messages on a topic this model does not draw (a prefix match of a subscription)
        self.not_kept = 0  # readings of elements beyond MAX_ELEMENTS, contacts beyond MAX_CONTACTS
        self.daemon_restarts = 0
        self.last_seq: dict[str, int] = {}
        self.last_message: float = -math.inf
        self.changed = True
        self.paused = False
        self._history_keep = HISTORY
        self._too_large: tuple[float, float] | None = None  # (cols, rows) of a layout beyond MAX_GRID
        self.needs_topology = True  # the shell asks the control socket for the layout while set
        self.skin: RobotSkin | None = None  # the skin on the robot (topology's ``skin``); None: a flat skin
        self.bad_fields = 0  # fields of readable payloads left out as unreadable (shown as unknown)
        self._index: tuple[int, dict[str, int], dict[tuple[int, int], list[int]]] | None = None
        self._layout_version = 0  # counts the layouts taken (the index above is of one)

    # ---- input --------------------------------------------------------------------

    def feed(self, topic: str, payload: Any, now: float) -> None:
        """One message from the PUB socket, decoded; ``now`` is the receiver's monotonic time.
        Never raises: a payload this model cannot read is counted in :attr:`malformed`."""
        if topic not in TOPICS:
            self.unknown_topics += 1
            return
        self.received[topic] = self.received.get(topic, 0) + 1
        if not isinstance(payload, dict):
            self.malformed += 1
            return
        if not self._shown(payload.get("source")):
            return
        self.last_message = now
        try:
            self._count_seq(topic, payload)
            if topic == "element":
                self._feed_element(payload)
            elif topic == "contact":
                self._feed_contact(payload)
            elif topic == "health":
                self._feed_health(payload)
            else:
                self._feed_topology(payload)
        except Exception:  # a payload nobody foresaw: counted, and the view goes on ("never a crash")
            self.malformed += 1
            return
        self.changed = True

    def feed_malformed(self, now: float) -> None:
        """A message that was not [topic, msgpack payload]: counted, never dropped silently.
        (It says nothing of which daemon sent it, so it does not count as a sign of life.)"""
        self.malformed += 1

    def _shown(self, source: Any) -> bool:
        """Whether a payload of ``source`` belongs to the picture (else it is counted)."""
        name = source if isinstance(source, str) else ""
        if self.source is None:
            self.source = name  # the first daemon heard is the one shown
        if name == self.source:
            return True
        if name in self.other_sources or len(self.other_sources) < MAX_OTHER_SOURCES:
            self.other_sources[name] = self.other_sources.get(name, 0) + 1
        else:
            self.other_sources_more += 1
        return False

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

    def feed_topology(self, payload: Any) -> None:
        """The reply of the control request ``topology`` (or a ``topology`` message's
        payload). Never raises: a reply this model cannot read is counted."""
        try:
            self._feed_topology(payload)
        except Exception:  # as in feed()
            self.malformed += 1

    def _feed_topology(self, payload: Any) -> None:
        layout = payload.get("layout") if isinstance(payload, dict) else None
        if not isinstance(layout, dict):
            return
        ids, xs, ys = layout.get("ids"), layout.get("x"), layout.get("y")
        if not (isinstance(ids, list) and isinstance(xs, list) and isinstance(ys, list)):
            return
        side = _num(layout.get("side"))
        if 0 < side <= MAX_SIDE:
            self.side = side
        placed: dict[int, tuple[float, float]] = {}
        for b, x, y in zip(ids[:MAX_COLUMN], xs, ys):
            bridge, px, py = _bridge(b), _pos(x), _pos(y)
            if bridge is None or not (math.isfinite(px) and math.isfinite(py)):
                continue
            if len(placed) >= MAX_ELEMENTS and bridge not in placed:
                continue  # a layout of more elements than are kept: the first ones drawn
            placed[bridge] = (px, py)
        self.layout = placed
        self._layout_version += 1
        if "skin" in payload:
            self.skin = read_skin(payload["skin"], MAX_ELEMENTS, MAX_BRIDGE)
            if self.skin is None and payload["skin"] is not None:
                self.bad_fields += 1
            elif self.skin is not None:
                self.bad_fields += self.skin.bad
        else:
            self.skin = None  # a daemon without skin descriptions (schema 1)
        self.needs_topology = not self.layout
        self.changed = True

    def _history_len(self, n: int) -> int:
        """Samples of history kept per element when ``n`` elements are kept: all
        :data:`HISTORY` up to 256 elements, then less, so that the total stays bounded."""
        return max(50, min(HISTORY, HISTORY_BUDGET // (1 << max(0, n - 1).bit_length())))

    def _element(self, b: int) -> Element | None:
        e = self.elements.get(b)
        if e is not None:
            return e
        if len(self.elements) >= MAX_ELEMENTS:
            self.not_kept += 1
            return None
        keep = self._history_len(len(self.elements) + 1)
        if keep != self._history_keep:  # at most once per doubling of the elements kept
            self._history_keep = keep
            for old in self.elements.values():
                old.history = deque(old.history, maxlen=keep)
        e = self.elements[b] = Element(b, history=deque(maxlen=keep))
        if b not in self.layout:
            self.needs_topology = True
        return e

    def _feed_element(self, p: dict[str, Any]) -> None:
        bridges = p.get("bridge")
        if not isinstance(bridges, list):
            raise ValueError("element without bridge column")
        bridges = bridges[:MAX_COLUMN]
        n = len(bridges)
        cols = [_col(p, k, n) for k in ("force", "area", "dc1", "dc2", "valid", "touched", "status", "t_sample")]
        for b, force, area, dc1, dc2, valid, touched, status, ts in zip(bridges, *cols):
            bridge = _bridge(b)
            e = self._element(bridge) if bridge is not None else None
            if e is None:
                continue
            e.force, e.area, e.dc1, e.dc2 = _num(force), _num(area), _num(dc1), _num(dc2)
            e.valid, e.touched = valid is True, touched is True
            e.status = status if isinstance(status, int) and not isinstance(status, bool) else 0
            e.t_sample = _num(ts)
            e.history.append((e.t_sample, e.shown_force(), e.dc1))

    def _feed_contact(self, p: dict[str, Any]) -> None:
        contacts = p.get("contacts")
        if not isinstance(contacts, list):
            raise ValueError("contact without contacts")
        out: list[Contact] = []
        for c in contacts[:MAX_COLUMN]:
            cid = c.get("id") if isinstance(c, dict) else None
            if not isinstance(cid, int) or isinstance(cid, bool):
                self.malformed += 1
                continue
            if len(out) >= MAX_CONTACTS:
                self.not_kept += 1
                continue
            obs = c.get("observable")
            observable = (obs[0] is not False, obs[1] is not False) if isinstance(obs, list) and len(obs) >= 2 \
                else (True, True)
            elements = c.get("elements")
            missed = c.get("missed")
            link, patch, position, normal, fvec = (self._opt(c, "link", _label), self._opt(c, "patch", _label),
                                                   self._opt(c, "position", vec3), self._opt(c, "normal", unit3),
                                                   self._opt(c, "force_vector", _force3))
            out.append(Contact(link=link, patch=patch, position=position, normal=normal, force_vector=fvec,
                               id=cid, x=_pos(c.get("x")), y=_pos(c.get("y")), force=_num(c.get("force")),
                               diameter=_size(c.get("diameter")), observable=observable,
                               valid=c.get("valid") is not False,
                               missed=missed if isinstance(missed, int) and not isinstance(missed, bool) else 0,
                               sigma_x=_size(c.get("sigma_x")), sigma_y=_size(c.get("sigma_y")),
                               elements=tuple(b for b in elements[:MAX_CONTACTS] if _bridge(b) is not None)
                               if isinstance(elements, list) else ()))
        self.contacts = out
        self.contact_t = _num(p.get("t_sample"))

    def _opt(self, c: dict[str, Any], key: str, read: Any) -> Any:
        """``read(c[key])``; None when absent or null, and None counted in
        :attr:`bad_fields` when present but unreadable."""
        v = c.get(key)
        if v is None:
            return None
        out = read(v)
        if out is None:
            self.bad_fields += 1
        return out

    def _feed_health(self, p: dict[str, Any]) -> None:
        summary = summarise_health(p)
        self.health = bounded(p)
        self.health_summary = summary
        self.health_count += 1

    def scale(self, factor: float) -> None:
        """Multiply both colour scales by ``factor`` (the views' +/- keys), within 1e-6..1e6."""
        self.force_scale = min(1e6, max(1e-6, self.force_scale * factor))
        self.dc_scale = min(1e6, max(1e-6, self.dc_scale * factor))
        self.changed = True

    # ---- output -------------------------------------------------------------------

    def live(self, now: float) -> bool:
        return now - self.last_message <= self.stale_after

    def frame(self, now: float) -> Frame:
        """What to draw now. Clears :attr:`changed`. The grid is at most :data:`MAX_GRID`
        cells a side for the layout, plus rows of unplaced elements (at most
        :data:`MAX_ELEMENTS` in all); a layout that would need a larger grid is drawn as
        unplaced elements, and a status line says so."""
        self.changed = False
        blocks = self._patch_blocks()
        if blocks is not None:
            return self._patch_frame(now, *blocks)
        placed = dict(self.layout)
        for b in self.elements:  # a bridge without a known position still shows, after the placed ones
            placed.setdefault(b, (math.nan, math.nan))
        side = self.side
        finite = [xy for xy in placed.values() if math.isfinite(xy[0])]
        xs, ys = [x for x, _ in finite], [y for _, y in finite]
        x0 = min(xs, default=0.0) - side / 2
        y0 = min(ys, default=0.0) - side / 2
        span = ((max(xs) - min(xs)) / side + 1, (max(ys) - min(ys)) / side + 1) if finite else (0.0, 0.0)
        fits = span[0] <= MAX_GRID and span[1] <= MAX_GRID  # False for inf and NaN too
        self._too_large = None if fits else span
        cells: list[Cell] = []
        rows = cols = 0
        unplaced = sorted(b for b, xy in placed.items() if not (fits and math.isfinite(xy[0])))
        if fits:
            for b, (x, y) in sorted(placed.items()):
                if not math.isfinite(x):
                    continue
                col, row = int(round((x - x0) / side - 0.5)), int(round((y - y0) / side - 0.5))
                cells.append(self._cell(b, row, col))
                rows, cols = max(rows, row + 1), max(cols, col + 1)
        per_row = max(cols, UNPLACED_PER_ROW)
        for i, b in enumerate(unplaced):  # extra rows beyond the skin
            cells.append(self._cell(b, rows + i // per_row, i % per_row))
        if unplaced:
            cols = max(cols, min(len(unplaced), per_row))
            rows += (len(unplaced) + per_row - 1) // per_row
        quantity = "force" if not cells or any(c.quantity == "force" for c in cells) else "dc"
        drawn = []
        for c in self.contacts:
            gx, gy = ((c.x - x0) / side, (c.y - y0) / side) if fits else (math.nan, math.nan)
            if not (-MAX_GRID <= gx <= 2 * MAX_GRID and -MAX_GRID <= gy <= 2 * MAX_GRID):
                gx = gy = math.nan  # far off the skin (or no position): listed, not drawn
            d = min(c.diameter / side, 2.0 * MAX_GRID) if math.isfinite(c.diameter) else 0.0
            level = min(1.0, max(0.0, c.force / self.force_scale)) if math.isfinite(c.force) else math.nan
            drawn.append(DrawnContact(
                id=c.id, col=gx, row=gy, diameter=d, level=level,
                force=c.force, x=c.x, y=c.y, diameter_m=c.diameter, observable=c.observable, valid=c.valid,
                label=f"#{c.id} {format_force(c.force)}", line=contact_line(c)))
        return Frame(rows=rows, cols=cols, side=side, origin=(x0, y0), quantity=quantity,
                     scale=self.force_scale if quantity == "force" else self.dc_scale, cells=cells,
                     contacts=drawn, status=self.status_lines(now), live=self.live(now), paused=self.paused,
                     counters=self.counters())

    def _patch_blocks(self) -> tuple[list[PatchBlock], int, int] | None:
        """The patches' blocks (see :func:`pack_patches`) when the layout comes with a skin
        on a robot whose patches fit the grid; None: draw the layout's plane (the atlas)."""
        skin = self.skin
        if skin is None or not skin.elements:
            return None
        blocks, rows, cols = pack_patches([p for p in skin.patches.values() if p.ids])
        if not blocks or rows > MAX_GRID or cols > MAX_GRID:
            return None
        for b in blocks:
            b.short = printable(b.name, 24)
            b.title = printable(b.link or "?", 24) + " / " + b.short + (" (around)" if b.wrap else "")
        return blocks, rows, cols

    def _patch_frame(self, now: float, blocks: list[PatchBlock], rows: int, cols: int) -> Frame:
        """The frame of a skin on a robot: each patch's elements on its own block of the
        grid (its rows and columns as on the patch), a title row above each; elements the
        skin description does not place in rows below; contacts on their patch's block."""
        skin = self.skin
        assert skin is not None
        at = {b.name: b for b in blocks}
        cells: list[Cell] = []
        unplaced: list[int] = []
        for b in sorted(set(self.layout) | set(self.elements)):
            place = skin.elements.get(b)
            block = at.get(place.patch) if place is not None else None
            if place is None or block is None:
                unplaced.append(b)
                continue
            cells.append(self._cell(b, block.row0 + place.row, block.col0 + place.col))
        if unplaced:  # below the patches: shift every block up
            per_row = max(cols, UNPLACED_PER_ROW)
            extra = (len(unplaced) + per_row - 1) // per_row + 1
            for cell in cells:
                cell.row += extra
            for blk in blocks:
                blk.row0 += extra
            for i, b in enumerate(unplaced):
                cells.append(self._cell(b, extra - 2 - i // per_row, i % per_row))
            rows += extra
            cols = max(cols, min(len(unplaced), per_row))
        quantity = "force" if not cells or any(c.quantity == "force" for c in cells) else "dc"
        drawn = []
        for c in self.contacts:
            gx, gy = self._on_patch(c, at)
            d = min(c.diameter / self.side, 2.0 * MAX_GRID) if math.isfinite(c.diameter) else 0.0
            level = min(1.0, max(0.0, c.force / self.force_scale)) if math.isfinite(c.force) else math.nan
            drawn.append(DrawnContact(
                id=c.id, col=gx, row=gy, diameter=d, level=level,
                force=c.force, x=c.x, y=c.y, diameter_m=c.diameter, observable=c.observable, valid=c.valid,
                label=f"#{c.id} {format_force(c.force)}", line=contact_line(c)))
        self._too_large = None
        x0 = min((xy[0] for xy in self.layout.values()), default=0.0) - self.side / 2
        y0 = min((xy[1] for xy in self.layout.values()), default=0.0) - self.side / 2
        return Frame(rows=rows, cols=cols, side=self.side, origin=(x0, y0), quantity=quantity,
                     scale=self.force_scale if quantity == "force" else self.dc_scale, cells=cells,
                     contacts=drawn, status=self.status_lines(now), live=self.live(now), paused=self.paused,
                     counters=self.counters(), patches=blocks)

    def _on_patch(self, c: Contact, at: dict[str, PatchBlock]) -> tuple[float, float]:
        """A contact's place on the grid of patch blocks (grid units, 0 the left and lower
        edge of cell 0): from its place on the layout's plane (the atlas, ``x``, ``y``),
        relative to an element of its patch (the one it names, else the nearest element's:
        a patch's grid is an affine map of the layout), one element pitch a cell, around a
        wrapped patch; NaN when not known, and when the link or patch it names is not the
        one of that place (a link or patch the topology lacks, a patch of another link):
        listed, never drawn on another link's patch."""
        skin = self.skin
        if skin is None or not (math.isfinite(c.x) and math.isfinite(c.y)):
            return math.nan, math.nan
        refs, cells = self._atlas_index()
        if c.patch is not None:  # the patch it names, which must be the skin's and on the link it names
            named = skin.patches.get(c.patch)
            if named is None or (c.link is not None and named.link != c.link):
                return math.nan, math.nan
        ref_bridge = refs.get(c.patch) if c.patch is not None else None  # any element of it: the map is affine
        if ref_bridge is None or ref_bridge not in self.layout:
            ref_bridge = self._nearest_placed(c.x, c.y, cells)
        if ref_bridge is None or skin.elements[ref_bridge].patch not in at:
            return math.nan, math.nan
        if c.link is not None and skin.patches[skin.elements[ref_bridge].patch].link != c.link:
            return math.nan, math.nan  # its link's patches are elsewhere (or it has none): not on another's
        ref = skin.elements[ref_bridge]
        patch, block = skin.patches[ref.patch], at[ref.patch]
        xe, ye = self.layout[ref_bridge]
        cp = patch.col_pitch if math.isfinite(patch.col_pitch) else self.side
        rp = patch.pitch if math.isfinite(patch.pitch) else self.side
        gcol = ref.col + 0.5 + (c.x - xe) / cp
        grow = ref.row + 0.5 + (c.y - ye) / rp
        if patch.wrap and patch.cols > 0:
            gcol %= patch.cols
        if not (-MAX_GRID <= gcol <= 2 * MAX_GRID and -MAX_GRID <= grow <= 2 * MAX_GRID):
            return math.nan, math.nan
        return block.col0 + gcol, block.row0 + grow

    def _atlas_index(self) -> tuple[dict[str, int], dict[tuple[int, int], list[int]]]:
        """(patch -> one of its elements on the layout, layout cell -> elements in it) of the
        skin's elements, built once per layout and skin: a contact is placed on its patch
        in constant time, whatever the skin's size."""
        key = self._layout_version
        if self._index is not None and self._index[0] == key:
            return self._index[1], self._index[2]
        refs: dict[str, int] = {}
        cells: dict[tuple[int, int], list[int]] = {}
        skin = self.skin
        for b, (x, y) in self.layout.items():
            place = skin.elements.get(b) if skin is not None else None
            if place is None:
                continue
            refs.setdefault(place.patch, b)
            cells.setdefault(self._cell_key(x, y), []).append(b)
        self._index = (key, refs, cells)
        return refs, cells

    def _cell_key(self, x: float, y: float) -> tuple[int, int]:
        """The layout cell (of the element side) holding (x, y); positions a side too
        small puts beyond 2**52 cells share the cell at the far end."""
        lim = float(2**52)
        return (math.floor(max(-lim, min(lim, x / self.side))), math.floor(max(-lim, min(lim, y / self.side))))

    def _nearest_placed(self, x: float, y: float, cells: dict[tuple[int, int], list[int]]) -> int | None:
        """The skin's element nearest (x, y) on the layout: among the 3 × 3 layout cells
        around it, else (a contact off every element) among all."""
        i, j = self._cell_key(x, y)
        near = [b for di in (-1, 0, 1) for dj in (-1, 0, 1) for b in cells.get((i + di, j + dj), ())]
        pool = near or [b for bs in cells.values() for b in bs]
        return min(pool, key=lambda b: (self.layout[b][0] - x) ** 2 + (self.layout[b][1] - y) ** 2, default=None)

    def _cell(self, bridge: int, row: int, col: int) -> Cell:
        """An element's force where the inverse gives one (0 when untouched); else its ΔC1
        (a light, ambiguous touch); else grey: "cal" while its baseline is taken, "?"."""
        e = self.elements.get(bridge)
        if e is None:
            return Cell(bridge, row, col, math.nan, "·", False, math.nan, math.nan)
        f = e.shown_force()
        if math.isfinite(f):
            return Cell(bridge, row, col, min(1.0, max(0.0, f / self.force_scale)), f"{fmt(f)}N" if f > 0 else "",
                        e.touched, f, e.dc1)
        dc = e.dc1 * 1e12
        if math.isfinite(dc):
            return Cell(bridge, row, col, min(1.0, max(0.0, dc / self.dc_scale)), f"{fmt(dc)}pF", e.touched, f,
                        e.dc1, quantity="dc")
        return Cell(bridge, row, col, math.nan, "cal" if e.status & 1 else "?", e.touched, f, e.dc1, quantity="none")

    def counters(self) -> dict[str, Any]:
        return {"received": dict(self.received), "lost": dict(self.lost), "malformed": self.malformed,
                "daemon_restarts": self.daemon_restarts,
                "other_sources": sum(self.other_sources.values()) + self.other_sources_more,
                "unknown_topics": self.unknown_topics, "not_kept": self.not_kept, "bad_fields": self.bad_fields}

    def status_lines(self, now: float) -> list[str]:
        """The status area: daemon, links, bridges, loss, rate, estimation time, this view's
        losses. Every string from the daemon in it has passed :func:`printable`."""
        h = self.health_summary
        lines = []
        if self._waiting_since is None:
            self._waiting_since = now
        if self.last_message == -math.inf and not self.received and now - self._waiting_since >= self.quiet_after:
            # nothing at all, not even health (every second from a running daemon): as `cellbridge sub` says it
            lines.append(f"daemon: no daemon answers on {printable(self.endpoint or '?')}")
            lines.append(f"  nothing in {self.quiet_after:g} s, not even its health: is it running? (waiting on)")
        elif self.last_message == -math.inf:
            lines.append("daemon: waiting for the first message"
                         + (f" of source {printable(self.source)}" if self.source_given else ""))
        elif not self.live(now):
            lines.append(f"daemon: SILENT for {fmt(now - self.last_message, '.0f')} s "
                         "(stopped? reconnecting by itself)")
        else:
            lines.append(f"daemon: live  uptime {fmt(h.get('uptime', math.nan), '.0f')} s"
                         + (f"  restarts seen {self.daemon_restarts}" if self.daemon_restarts else ""))
        if self.other_sources or self.other_sources_more:
            others = ", ".join(f"{printable(n, 30) or '(unnamed)'} ({k})" for n, k in sorted(self.other_sources.items()))
            more = f", more: {self.other_sources_more}" if self.other_sources_more else ""
            shown = printable(self.source, 30) or "(unnamed)"
            lines.append(f"source: {shown}{'' if self.source_given else ' (the first heard)'}; "
                         f"not shown: {others}{more} (pick with --source)")
        if h:
            lines.append(f"links: {h['links_up']}/{h['links']} up  {h['link_text']}")
            lines.append(f"bridges: {h['alive']} alive, {h['silent']} silent  loss {fmt(h['loss'] * 100, '.2f')} %  "
                         f"rate {fmt(h['rate'], '.0f')} samples/s")
            lines.append(f"contacts: estimate {fmt(h['est_ms'], '.2f')} ms (max {fmt(h['est_max_ms'], '.2f')})  "
                         f"calibration {h['calibration']}")
        if self._too_large is not None:
            lines.append(f"layout: {fmt(self._too_large[0], '.0f')} x {fmt(self._too_large[1], '.0f')} elements "
                         f"of {fmt(self.side * 1e3, '.2f')} mm, beyond the {MAX_GRID} x {MAX_GRID} drawn: "
                         "elements shown unplaced")
        if self.skin is not None:
            links = {p.link for p in self.skin.patches.values() if p.ids}
            lines.append(f"skin: {printable(self.skin.name, 24) or '?'}, {len(self.skin.elements)} elements "
                         f"in {sum(1 for p in self.skin.patches.values() if p.ids)} patches on {len(links)} links"
                         + ("" if self._patch_blocks() is not None else " (drawn as the layout's plane)"))
        lost = sum(self.lost.values())
        lines.append(f"this view: {sum(self.received.values())} messages, lost {lost}"
                     + (f"  (daemon dropped {fmt(h['pub_dropped'], '.0f')})" if h.get("pub_dropped") else "")
                     + (f" ({', '.join(f'{k} {v}' for k, v in sorted(self.lost.items()))})" if lost else "")
                     + (f", malformed {self.malformed}" if self.malformed else "")
                     + (f", beyond limits {self.not_kept}" if self.not_kept else "")
                     + (f", unreadable fields {self.bad_fields}" if self.bad_fields else "")
                     + (f", other topics {self.unknown_topics}" if self.unknown_topics else "")
                     + ("  [PAUSED]" if self.paused else ""))
        return lines


def _table(p: dict[str, Any], key: str) -> dict[Any, Any]:
    """``p[key]`` when it is a map, else an empty one."""
    v = p.get(key)
    return v if isinstance(v, dict) else {}


def _total(values: Any) -> float:
    """The sum of the numbers among ``values`` (anything else is taken as absent); NaN
    (shown as ``?``) when one of them is not finite: a sum it enters is not known."""
    total = 0.0
    for v in values:
        x = _num(v)
        if not math.isnan(x) or isinstance(v, float):
            total += x
    return total if math.isfinite(total) else math.nan


def _name(key: Any) -> str:
    """A map key (a link's name) as text to show."""
    return printable(key, 24) if isinstance(key, str) else str(key) if isinstance(key, int) else printable(key)


def _shown_value(v: Any) -> str:
    """A scalar from the daemon as short text: numbers formatted, strings escaped."""
    if isinstance(v, bool) or v is None:
        return "?"
    if isinstance(v, int):
        return fmt(float(v), ".0f") if abs(v) >= 1e6 else str(v)
    if isinstance(v, float):
        return fmt(v, "g")
    return printable(v, 12) if isinstance(v, str) else "?"


def summarise_health(p: dict[str, Any]) -> dict[str, Any]:
    """The few figures of a ``health`` payload a status area shows (defensive: any may be
    absent or of any type; sums that overflow show as such, never raise)."""
    links = _table(p, "links")
    bridges = _table(p, "bridges")
    up = {n for n, ln in links.items() if isinstance(ln, dict) and ln.get("connected") is True}
    silent = sum(1 for br in bridges.values() if isinstance(br, dict) and br.get("silent") is True)
    rows = [br for br in bridges.values() if isinstance(br, dict)]
    lost = _total(br.get("lost") for br in rows)
    frames = _total(br.get("frames") for br in rows)
    rate = _total(br.get("sample_rate") for br in rows)
    est = _table(p, "contact_estimation")
    cal = _table(_table(p, "layout"), "calibration")
    dropped = _table(_table(p, "pub"), "dropped")
    shown = sorted(((_name(n), n in up) for n in links), key=lambda t: t[0])[:4]
    link_text = "  ".join(f"{n}:{'up' if ok else 'DOWN'}" for n, ok in shown)
    seen = lost + frames
    loss = lost / seen if seen > 0 else 0.0 if seen == 0 else math.nan  # NaN: a count not known
    return {
        "uptime": _num(p.get("uptime")),
        "links": len(links), "links_up": len(up), "link_text": link_text,
        "alive": len(bridges) - silent, "silent": silent,
        "loss": loss,
        "rate": rate,
        "est_ms": _num(est.get("last_ms")), "est_max_ms": _num(est.get("max_ms")),
        "calibration": (f"{_shown_value(cal.get('ready', '?'))} ready, {_shown_value(cal.get('collecting', 0))} collecting"
                        if cal else "?"),
        "pub_dropped": _total(dropped.values()),
    }

"""The world: what presses on the skin, and the capacitance each element then has.

Contacts are disks (force, diameter) that start, last, and may move in a straight
line. Their effect on every element goes through :func:`cellbridge.tactile.skin_response`
(exact share of each disk on each element at pressure F/S), so a press straddling
two elements gives each the right ΔC1/ΔC2. The same object serves a scenario file
(all contacts known ahead) and live injection (``press`` while the mesh runs).

Scenario files (TOML)::

    [[contact]]
    start = 0.5              # s after the mesh starts
    duration = 1.0           # s
    position = [0.04, 0.0]   # centre at the start (m)
    force = 2.0              # N
    diameter = 0.02          # m
    velocity = [0.01, 0.0]   # optional, m/s
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, replace
from typing import Any, Callable, Mapping

import numpy as np
from cellbridge.emulator.mesh.mesh import Mesh, read_text
from cellbridge.tactile import ElementParams, SkinLayout, skin_response

from cellbridge.errors import CellbridgeError

#: Sets of active contacts whose capacitances a world keeps (:meth:`World._pressed`)
_RESPONSES_KEPT = 8
_CONTACT_KEYS = {"start", "duration", "position", "force", "diameter", "velocity"}


class ScenarioError(CellbridgeError, ValueError):
    """A scenario that cannot be used; the message names the key and the problem."""


@dataclass(frozen=True)
class Contact:
    start: float
    duration: float
    x: float
    y: float
    force: float
    diameter: float
    vx: float = 0.0
    vy: float = 0.0

    def active(self, t: float) -> bool:
        return self.start <= t < self.start + self.duration

    def at(self, t: float) -> tuple[float, float, float, float]:
        dt = t - self.start
        return (self.x + self.vx * dt, self.y + self.vy * dt, self.force, self.diameter)


@dataclass(frozen=True)
class Drift:
    """One element's capacitances changing by themselves, at a steady rate from ``start``
    for ``duration`` seconds (then held): a parasitic moving with temperature (one
    channel) or a foam's permittivity (both). Nothing presses; the daemon must not
    report a contact for it. Rates in F/s per channel."""

    bridge: int
    start: float
    rate1: float  #: F/s on C1
    rate2: float  #: F/s on C2
    duration: float = math.inf

    def offset(self, t: float) -> tuple[float, float]:
        """(ΔC1, ΔC2) the drift has added by time ``t`` (s)."""
        dt = min(max(t - self.start, 0.0), self.duration)
        return self.rate1 * dt, self.rate2 * dt


def _num(e: Mapping[str, Any], key: str, where: str, lo: float, strict: bool = False) -> float:
    if key not in e:
        raise ScenarioError(f"{where}: missing key '{key}'")
    v = e[key]
    if type(v) not in (int, float) or not math.isfinite(v) or v < lo or (strict and v == lo):
        raise ScenarioError(f"{where}.{key}: must be a number {'>' if strict else '>='} {lo}, got {v!r}")
    return float(v)


def _pair(e: Mapping[str, Any], key: str, where: str) -> tuple[float, float]:
    v = e[key]
    if not isinstance(v, list) or len(v) != 2 or not all(type(x) in (int, float) and math.isfinite(x) for x in v):
        raise ScenarioError(f"{where}.{key}: must be [x, y], got {v!r}")
    return float(v[0]), float(v[1])


def contact_from_mapping(e: Mapping[str, Any], where: str) -> Contact:
    extra = sorted(set(e) - _CONTACT_KEYS)
    if extra:
        raise ScenarioError(f"{where}: unknown key '{extra[0]}' (allowed: {', '.join(sorted(_CONTACT_KEYS))})")
    if "position" not in e:
        raise ScenarioError(f"{where}: missing key 'position'")
    x, y = _pair(e, "position", where)
    vx, vy = _pair(e, "velocity", where) if "velocity" in e else (0.0, 0.0)
    c = Contact(_num(e, "start", where, 0.0), _num(e, "duration", where, 0.0, True), x, y,
                _num(e, "force", where, 0.0, True), _num(e, "diameter", where, 0.0, True), vx, vy)
    if not _track_finite(c):
        raise ScenarioError(f"{where}.velocity: {[vx, vy]!r} for {c.duration} s moves the contact beyond "
                            f"the finite numbers (its position would be inf)")
    return c


def _track_finite(c: Contact) -> bool:
    # the position is linear in time: finite at both ends of the contact, finite between
    return math.isfinite(c.x + c.vx * c.duration) and math.isfinite(c.y + c.vy * c.duration)


def contact_problem(c: Contact) -> str | None:
    """Why ``c`` cannot be sampled (the skin model refuses it, at the first sample that
    sees it), or None. For contacts that come from elsewhere, e.g. over the wire: one
    that fails would stop every process sampling it."""
    if not all(math.isfinite(v) for v in (c.start, c.duration, c.x, c.y, c.force, c.diameter, c.vx, c.vy)):
        return "a value is not finite"
    if not (c.duration > 0 and c.force >= 0 and c.diameter > 0):
        return "duration and diameter must be > 0, force >= 0"
    if not _track_finite(c):
        return "its track leaves the finite numbers"
    return None


def touched(mesh: Mesh, c: Contact) -> list[int]:
    """Bridges whose element the contact's disk overlaps at some moment of its path
    (checked every half element along a moving contact's track)."""
    r, half = c.diameter / 2, mesh.side / 2
    length = math.hypot(c.vx, c.vy) * c.duration
    steps = min(10_000, int(length / half) + 1) if math.isfinite(length) else 10_000
    dt = c.duration / steps if steps > 1 else 0.0
    pts = np.array([b.position for b in mesh.bridges])
    hit = np.zeros(len(pts), dtype=bool)
    with np.errstate(over="ignore", invalid="ignore"):  # a contact far off: inf, not a hit
        for k in range(steps + 1 if steps > 1 else 1):
            x, y = c.x + c.vx * dt * k, c.y + c.vy * dt * k
            dx = np.maximum(np.abs(pts[:, 0] - x) - half, 0.0)  # distance from the disk centre
            dy = np.maximum(np.abs(pts[:, 1] - y) - half, 0.0)  # to each element's square
            hit |= dx * dx + dy * dy < r * r
    return [b.id for b, h in zip(mesh.bridges, hit) if h]


def check_on_skin(mesh: Mesh, c: Contact, where: str) -> None:
    """ScenarioError when the contact touches no element: a press beside the skin (a
    typo in a coordinate, metres taken for millimetres) would otherwise do nothing."""
    if not touched(mesh, c):
        pts = np.array([b.position for b in mesh.bridges])
        half = mesh.side / 2
        raise ScenarioError(
            f"{where}: a {c.diameter} m contact at ({c.x}, {c.y}) touches no element; the skin spans "
            f"x {pts[:, 0].min() - half:g}..{pts[:, 0].max() + half:g}, "
            f"y {pts[:, 1].min() - half:g}..{pts[:, 1].max() + half:g} m")


def parse_scenario(text: str, source: str = "scenario") -> list[Contact]:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{source}: not valid TOML: {exc}") from None
    except RecursionError:  # tomllib parses nested arrays and tables recursively
        raise ScenarioError(f"{source}: not valid TOML: nested too deeply") from None
    extra = sorted(set(data) - {"contact"})
    if extra:
        raise ScenarioError(f"{source}: unknown key '{extra[0]}' (a scenario holds [[contact]] tables)")
    raw = data.get("contact", [])
    if not isinstance(raw, list):
        raise ScenarioError(f"{source}: 'contact' must be an array of tables ([[contact]])")
    return [contact_from_mapping(e, f"{source}: contact[{i}]") for i, e in enumerate(raw)]


def load_scenario(path: str) -> list[Contact]:
    return parse_scenario(read_text(path, "scenario", ScenarioError), path)


class World:
    """Element capacitances of a mesh's skin over time (one element per bridge)."""

    def __init__(self, mesh: Mesh, contacts: list[Contact] | None = None,
                 params: ElementParams | None = None, clock_hz: int = 50_000_000,
                 quantum: float = 1e-3, bridges: list[int] | None = None,
                 drifts: list[Drift] | None = None) -> None:
        """``bridges`` limits the elements evaluated (a bridge process needs only its own:
        without membrane spread an element's response depends on nothing else);
        ``drifts``: elements whose capacitances change by themselves (ValueError for a
        bridge not in the mesh)."""
        self.params = params or ElementParams(side=mesh.side)
        ids = list(mesh.ids if bridges is None else bridges)
        self.layout = SkinLayout(np.array([mesh.bridge(b).position for b in ids]), mesh.side, np.array(ids))
        self.index = {b: i for i, b in enumerate(ids)}
        self.contacts: list[Contact] = list(contacts or [])
        self._published: list[Contact] | None = None  #: the list set_contacts was last given
        unknown = sorted({d.bridge for d in drifts or []} - set(mesh.ids))
        if unknown:
            raise ValueError(f"drift on bridge {unknown[0]}, which is not in the mesh")
        self.drifts = [d for d in drifts or [] if d.bridge in self.index]
        self.clock_hz = clock_hz
        self.quantum = quantum  # moving contacts are re-evaluated at most this often
        self.wraps = mesh.wraps  # bands that close on themselves: a press across the seam presses both ends
        self.side = mesh.side
        self.rest = (self.params.C1_rest, self.params.C2_rest)
        #: a stimulus's key -> (C1, C2): :meth:`_cached`'s values, oldest first
        self._responses: dict[object, tuple[np.ndarray, np.ndarray]] = {}
        self._extent = self.layout.extent

    def press(self, contact: Contact) -> None:
        self.contacts.append(contact)

    def set_contacts(self, contacts: list[Contact], at: float | None = None, keep: float = 2.0) -> None:
        """Replace every contact (a bridge process mirroring the world process's list).

        ``at``: when (s, the contacts' clock) the new list takes over. A contact it no
        longer holds (a world that restarted without it) stays as it was before ``at``,
        ending then at the latest, for ``keep`` seconds after its end: a bridge computes a
        sample lazily, after its gate (a relay's readout sample at its children's records,
        a DATA batch at its frame), and that sample must see what pressed at its gate, not
        what the world said afterwards. A contact the new list holds counts from its own
        start, even one before ``at`` (the press began then; the world said so late).
        None: the old contacts are forgotten at once (a world that knows its whole past)."""
        new = list(contacts)
        if new == self._published:
            return
        self._published = list(new)
        if at is not None:
            kept = []
            for c in self.contacts:
                end = c.start + c.duration
                if c in new or end <= at - keep or c.start >= at:
                    continue  # still there, long over, or not begun when it was taken back
                if any(n.start == c.start and n.x == c.x and n.y == c.y for n in new):
                    continue  # the same press, as the new list has it
                kept.append(c if end <= at else replace(c, duration=at - c.start))
            new = kept + new
        if new != self.contacts:
            self.contacts = new

    def capacitances(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(C1, C2) of every element at time ``t`` (s), parasitics and drifts included."""
        c1, c2 = self._pressed(t)
        if not self.drifts:
            return c1, c2
        c1, c2 = c1.copy(), c2.copy()
        for d in self.drifts:
            o1, o2 = d.offset(t)
            c1[self.index[d.bridge]] += o1
            c2[self.index[d.bridge]] += o2
        return c1, c2

    def _pressed(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(C1, C2) of every element at ``t`` from the contacts alone (cached per set of
        active contacts and, for moving ones, per quantum: a few sets are kept, so a sample
        of a gate before a press, computed lazily after the press came, does not evict the
        press's own values, nor they it)."""
        active = tuple(c for c in self.contacts if c.active(t))
        moving = any(c.vx or c.vy for c in active)
        q = math.floor(t / self.quantum) if moving else None
        return self._cached((active, q), lambda: self._respond(active, t if q is None else q * self.quantum))

    def _cached(self, key: object, compute: Callable[[], tuple[np.ndarray, np.ndarray]]
                ) -> tuple[np.ndarray, np.ndarray]:
        """The (C1, C2) a stimulus named by ``key`` gives (a function of the key alone),
        computed by ``compute`` the first time; the last ``_RESPONSES_KEPT`` are kept."""
        got = self._responses.get(key)
        if got is None:
            got = compute()
            if len(self._responses) >= _RESPONSES_KEPT:
                self._responses.pop(next(iter(self._responses)))  # the oldest
            self._responses[key] = got
        return got

    def _respond(self, active: tuple[Contact, ...], when: float) -> tuple[np.ndarray, np.ndarray]:
        """(C1, C2) of every element under ``active`` placed where they are at ``when``
        (moving contacts where they are at the quantum's start, whoever asks first: a
        sample's capacitance is a function of its gate's time alone, not of the order the
        bridges, a prefetch or a lazy sample asked in). A disk wholly outside the bounding
        box of this world's elements touches none of them and is left out: a bridge
        process's world holds its own element only, and the skin response of a press
        elsewhere (most presses, for most bridges) costs a millisecond of a cold process
        for nothing but rounding."""
        disks = self.disks([c.at(when) for c in active])
        x0, y0, x1, y1 = self._extent
        disks = [d for d in disks
                 if not (d[0] + d[3] / 2 < x0 or d[0] - d[3] / 2 > x1 or d[1] + d[3] / 2 < y0 or d[1] - d[3] / 2 > y1)]
        if not disks:
            return np.full(self.layout.n, self.rest[0]), np.full(self.layout.n, self.rest[1])
        d1, d2 = skin_response(self.layout, disks, self.params)
        return self.rest[0] + d1, self.rest[1] + d2

    def prepare(self, t: float) -> None:
        """Compute now the capacitances samples from ``t`` (s) on will ask for: those of
        the contacts active at ``t`` and at each of the next contacts' starts and ends
        (a few). Changes no value, only when the work runs: a bridge process calls it in
        the wake the world's new contacts bring (a press's start, about half a sampling
        period before its first gate), so the first sample that shows the press, and
        every relay's sample on its way to the gateway, is not held up by it."""
        instants = sorted({t, *(e for c in self.contacts for e in (c.start, c.start + c.duration) if e > t)})
        for e in instants[:_RESPONSES_KEPT // 2]:
            self._pressed(e)

    def disks(self, disks: list[tuple[float, float, float, float]]) -> list[tuple[float, float, float, float]]:
        """The ``(x, y, force, diameter)`` disks with their copies one band over, where a
        disk reaches across a wrap seam (:meth:`Band.ghosts`)."""
        if not self.wraps:
            return disks
        out = list(disks)
        for band in self.wraps:
            out += band.ghosts(disks, self.side)
        return out

    def sense_for(self, bridge: int):
        """``sense(tick) -> (C1, C2)`` of one bridge's element, for its firmware."""
        i = self.index[bridge]
        clock = float(self.clock_hz)

        def sense(tick: int) -> tuple[float, float]:
            if not self.contacts and not self.drifts:
                return self.rest
            c1, c2 = self.capacitances(tick / clock)
            return float(c1[i]), float(c2[i])

        return sense

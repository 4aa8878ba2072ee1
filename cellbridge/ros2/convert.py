"""The daemon's messages as ROS 2 messages: the core of ``cellbridge ros2`` and of ROS 2 bags.

Sans-I/O: :class:`Converter` is fed the decoded payloads of the daemon's topics
(``docs/zmq-api.md``) with a time, and returns the ROS 2 messages (:mod:`cellbridge.ros2.types`)
they make, by topic key (:mod:`cellbridge.ros2.qos`):

- ``element`` -> ``state``: a ``tactile_msgs/TactileState`` with every element's newest
  reading, one ``sensor_msgs/ChannelFloat32`` per quantity, one value per element in
  ascending element id: ``<frame>`` force (N), ``<frame>/area`` (m²), ``<frame>/dc1`` and
  ``<frame>/dc2`` (F, change from the baseline), ``<frame>/element`` (the element ids, so
  nobody has to guess the order). An untouched element reads 0 N; an element whose
  force is not known (no reading yet, baseline being taken, the inverse has no unique
  answer) reads NaN. Stamped with the newest sample time of the daemon's message.
- ``contact`` -> ``contacts``: a ``tactile_msgs/TactileContacts``, one ``TactileContact``
  per contact: ``name`` ``contact_<id>``, ``position`` and ``normal`` (out of the skin) in
  its frame (a flat skin: (x, y, 0) and (0, 0, 1)), ``wrench`` the force the contact
  applies *to* the skin (-F times the normal) and its torque about the frame's origin
  (position × force), as tactile_toolbox's own contact estimation fills it. A contact
  without pressure (``valid`` false) has a NaN wrench: its position alone is known. A
  contact on a link whose ``position`` (or ``normal``) did not come whole and finite has
  a NaN position (or normal and force), is not drawn, and is counted in
  :attr:`Converter.malformed`: its ``x``, ``y`` are a place on the unrolled patches, not
  in the link's frame. Stamped with the skin frame the contacts were estimated on
  (``t_sample``). An empty list says the contacts ended.
- ``health`` -> ``diagnostics``: a ``diagnostic_msgs/DiagnosticArray``: the daemon (OK,
  WARN when a bridge is silent or losing frames or this subscriber lost messages since the
  diagnostics before, ERROR
  when a link is down), each link and each bridge. At most every ``diagnostics_period``
  s of the fed time (ROS 2's diagnostic tools expect about one a second; a 16x16 skin's
  array costs ~25 ms to build and encode), and whenever the daemon's level changes; the
  health messages left out are counted in :attr:`Converter.diagnostics_skipped`.
- ``markers`` (from all of them, at most every ``marker_period`` s of the fed time, and
  whenever the number of contacts changes): a ``visualization_msgs/MarkerArray``, the
  skin's picture: a flat box per element coloured by force (the views' colour ramp),
  a disk per contact (its fitted diameter), an arrow for its force (1 cm per N, into the
  skin) and a label (as ``cellbridge watch`` writes it: an axis the readings cannot
  resolve is said to be unresolved).

Frames: everything is in one frame, ``frame_id`` (default ``cellbridge_skin``: the layout's
plane, metres, z out of the skin), except a contact whose map names its own ``link``,
which is then its frame (a skin on a robot's links).

Nothing here raises on a payload: a payload that is not what the API says is counted
in :attr:`Converter.malformed`. A payload of a schema version newer than the one this
converter was written for (``v`` above :data:`SCHEMA_VERSION`: a version that removes or
redefines a field, docs/zmq-api.md) is counted in :attr:`Converter.newer_schema` and makes
nothing: its fields may not mean what they say here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import islice
from typing import Any

from cellbridge.ros2 import DEFAULT_FRAME
from cellbridge.ros2 import types as T
from cellbridge.tactile.skin_geometry import frame_name
from cellbridge.views.model import (
    MAX_BRIDGE,
    MAX_CONTACTS,
    MAX_ELEMENTS,
    UNTOUCHED,
    Contact,
    contact_line,
    level_rgb,
    summarise_health,
)
from cellbridge.views.robot_skin import unit3, vec3

SCHEMA_VERSION = 2  # the daemon's payload schema this reads (docs/zmq-api.md, "Versioning")
MARKER_PERIOD = 0.1  # s: at most 10 pictures a second (a 16x16 skin's picture costs ~10 ms to build and encode)
ARROW_PER_NEWTON = 0.01  # m of arrow per N
UP = (0.0, 0.0, 1.0)
NOWHERE = (math.nan, math.nan, math.nan)
INT32 = 2**31  # a marker's id is an int32
LOSS_WARN = 0.05  # a bridge losing more than this fraction of its frames is a warning
#: The largest finite float32: a reading's channels are float32, and a value past it cannot be written
#: (the encoder raises): such a reading is unknown (NaN) and counted, never the end of the relay or the bag.
F32_MAX = 3.4028234663852886e38
MAX_HEALTH_BRIDGES = MAX_ELEMENTS + 64  # bridges a health message is read for: a 64x64 skin's and 64 strangers


def _num(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return math.nan
    return float(value)


def _col(payload: dict[str, Any], key: str, n: int) -> list[Any]:
    col = payload.get(key)
    if not isinstance(col, list):
        return [None] * n
    return col[:n] + [None] * (n - len(col))


@dataclass
class Reading:
    """An element's newest reading, as the ROS 2 messages give it."""

    force: float = math.nan
    area: float = math.nan
    dc1: float = math.nan
    dc2: float = math.nan


class Converter:
    """Daemon payloads in, ROS 2 messages out. ``frame_id``: the flat skin's frame."""

    def __init__(self, frame_id: str = DEFAULT_FRAME, marker_period: float = MARKER_PERIOD,
                 force_scale: float = 5.0, diagnostics_period: float = 0.0) -> None:
        self.frame_id = frame_id
        self.marker_period = marker_period
        self.diagnostics_period = diagnostics_period
        self.diagnostics_skipped = 0  # health messages that made no diagnostics (diagnostics_period)
        self._diagnostics_at = -math.inf
        self._diagnostics_level = -1
        self.force_scale = force_scale
        self.readings: dict[int, Reading] = {}
        self.layout: dict[int, tuple[float, float]] = {}
        self.side = 0.04
        self.contacts: list[dict[str, Any]] = []
        self.lost: dict[str, int] = {}  # the shell's: messages its subscriber lost, shown in diagnostics
        self._lost_published = 0  # sum(lost) when the diagnostics last went out
        self.malformed = 0
        self._counted_layout: Any = None  # the last layout counted as beyond the bound
        self.newer_schema = 0  # payloads of a schema version after SCHEMA_VERSION: not converted
        self.made: dict[str, int] = {}
        self._marker_at = -math.inf
        self._drawn_contacts = -1

    # ---- input ------------------------------------------------------------------------------

    def feed(self, topic: str, payload: Any, now: float) -> list[tuple[str, Any]]:
        """One daemon message (decoded msgpack) at time ``now`` (s; the markers' rate is
        counted on it): the ROS 2 messages it makes, as ``(topic key, message)``."""
        if not isinstance(payload, dict):
            self.malformed += 1
            return []
        if newer_schema(payload):
            self.newer_schema += 1
            return []
        out: list[tuple[str, Any]] = []
        try:
            if topic == "element":
                out.append(("state", self._element(payload)))
            elif topic == "contact":
                out.append(("contacts", self._contact(payload)))
            elif topic == "health":
                diag = self._health(payload, now)
                if diag is None:
                    self.diagnostics_skipped += 1
                    return []
                out.append(("diagnostics", diag))
            elif topic == "topology":
                self.set_layout(payload)
            else:
                return []
        except (TypeError, ValueError, KeyError, AttributeError, ArithmeticError):
            self.malformed += 1
            return []
        if topic in ("element", "contact", "topology") and self.layout:
            stamp = _num(payload.get("t_sample")) if topic == "contact" else _num(payload.get("t_host"))
            if now - self._marker_at >= self.marker_period or len(self.contacts) != self._drawn_contacts:
                self._marker_at = now
                self._drawn_contacts = len(self.contacts)
                out.append(("markers", self.markers(stamp)))
        for key, _ in out:
            self.made[key] = self.made.get(key, 0) + 1
        return out

    def set_layout(self, payload: dict[str, Any]) -> None:
        """A ``topology`` message or the control ``topology`` reply: where the elements are."""
        layout = payload.get("layout")
        if not isinstance(layout, dict):
            return
        ids, xs, ys = layout.get("ids"), layout.get("x"), layout.get("y")
        if not (isinstance(ids, list) and isinstance(xs, list) and isinstance(ys, list)):
            return
        side = _num(layout.get("side"))
        if math.isfinite(side) and side > 0:
            self.side = side
        self.layout = {b: (_num(x), _num(y)) for b, x, y in zip(ids, xs, ys)
                       if b.__class__ is int and 0 <= b <= MAX_BRIDGE
                       and math.isfinite(_num(x)) and math.isfinite(_num(y))}
        if len(self.layout) > MAX_ELEMENTS:  # the views' bound (a 64x64 skin): every picture draws them all
            self.layout = dict(sorted(self.layout.items())[:MAX_ELEMENTS])
            if layout is not self._counted_layout:  # (the control reply and the message may be one payload)
                self._counted_layout = layout
                self.malformed += 1
        if self.layout:  # an element the layout no longer has (a smaller skin, a rebuilt layout) is gone:
            # its last reading is not the skin's any more
            self.readings = {b: r for b, r in self.readings.items() if b in self.layout}

    # ---- element ----------------------------------------------------------------------------

    def _element(self, p: dict[str, Any]) -> T.TactileState:
        bridges = p.get("bridge")
        if not isinstance(bridges, list):
            raise ValueError("element without bridge column")
        n = len(bridges)
        newest = -math.inf
        cols = [_col(p, k, n) for k in ("force", "area", "dc1", "dc2", "valid", "touched", "status", "t_sample")]
        beyond = False  # a value no float32 holds, or an id no bridge has: counted once for the message
        for b, force, area, dc1, dc2, valid, touched, status, ts in zip(bridges, *cols):
            if b.__class__ is not int or not 0 <= b <= MAX_BRIDGE:
                beyond = beyond or (isinstance(b, int) and not isinstance(b, bool))
                continue
            r = self.readings.get(b)
            if r is None:
                if len(self.readings) >= MAX_ELEMENTS:  # the views' bound: readings of further ids are counted
                    beyond = True
                    continue
                r = self.readings[b] = Reading()
            # (floats as they come, the rest through _num: this loop runs 256 times a message on a 16x16 skin;
            # -F32_MAX <= v <= F32_MAX is false for NaN, the infinities and what float32 cannot hold)
            f = force if force.__class__ is float else _num(force)
            if valid is True and -F32_MAX <= f <= F32_MAX:
                a = area if area.__class__ is float else _num(area)
                if a > F32_MAX or a < -F32_MAX:
                    a, beyond = math.nan, True
                r.force, r.area = f, a
            elif status.__class__ is int and status & UNTOUCHED and touched is not True:
                r.force, r.area = 0.0, 0.0
            else:
                beyond = beyond or (valid is True and f == f and f not in (math.inf, -math.inf))
                r.force, r.area = math.nan, math.nan
            d1 = dc1 if dc1.__class__ is float else _num(dc1)
            d2 = dc2 if dc2.__class__ is float else _num(dc2)
            if d1 > F32_MAX or d1 < -F32_MAX or d2 > F32_MAX or d2 < -F32_MAX:
                beyond = True
                d1 = d1 if -F32_MAX <= d1 <= F32_MAX else math.nan
                d2 = d2 if -F32_MAX <= d2 <= F32_MAX else math.nan
            r.dc1, r.dc2 = d1, d2
            t = ts if ts.__class__ is float else _num(ts)
            if t > newest and t != math.inf:
                newest = t
        if beyond:
            self.malformed += 1
        if not math.isfinite(newest):
            newest = _num(p.get("t_host"))
        return self.state(newest)

    def state(self, t: float) -> T.TactileState:
        """Every element's newest reading as a TactileState stamped ``t``."""
        ids = sorted(set(self.layout) | set(self.readings))
        rs = [self.readings.get(b, Reading()) for b in ids]
        f = self.frame_id
        return T.TactileState(header=T.Header(stamp=T.stamp(t), frame_id=f), sensors=[
            T.ChannelFloat32(f, [r.force for r in rs]),
            T.ChannelFloat32(f"{f}/area", [r.area for r in rs]),
            T.ChannelFloat32(f"{f}/dc1", [r.dc1 for r in rs]),
            T.ChannelFloat32(f"{f}/dc2", [r.dc2 for r in rs]),
            T.ChannelFloat32(f"{f}/element", [float(b) for b in ids]),
        ])

    # ---- contact ----------------------------------------------------------------------------

    def _contact(self, p: dict[str, Any]) -> T.TactileContacts:
        contacts = p.get("contacts")
        if not isinstance(contacts, list):
            raise ValueError("contact without contacts")
        t = _num(p.get("t_sample"))
        if not math.isfinite(t):
            t = _num(p.get("t_host"))
        stamp = T.stamp(t)
        kept, out = [], []
        if len(contacts) > MAX_ELEMENTS:  # more contacts than a 64x64 skin has elements: a bound, as the
            # views keep one (converting 20 000 took seconds, and the relay sends contacts first)
            self.malformed += 1
            contacts = contacts[:MAX_ELEMENTS]
        for c in contacts:
            if not isinstance(c, dict) or not isinstance(c.get("id"), int) or isinstance(c.get("id"), bool):
                self.malformed += 1
                continue
            if not _place(c)[2]:
                self.malformed += 1  # on a link, but not where or not which way: listed, its place unknown
            kept.append(c)
            out.append(self.tactile_contact(c, stamp))
        self.contacts = kept
        return T.TactileContacts(contacts=out)

    def frame_of(self, c: dict[str, Any]) -> str:
        """The frame a contact is in: its own ``link`` when the daemon names one, else the skin's."""
        return frame_name(c.get("link")) or self.frame_id

    def tactile_contact(self, c: dict[str, Any], stamp: T.Time) -> T.TactileContact:
        (px, py, pz), n, _ = _place(c)
        force = _num(c.get("force")) if c.get("valid") is not False else math.nan
        fx, fy, fz = -force * n[0], -force * n[1], -force * n[2]
        return T.TactileContact(
            header=T.Header(stamp=stamp, frame_id=self.frame_of(c)), name=f"contact_{c['id']}",
            position=T.Point(px, py, pz), normal=T.Vector3(*n),
            wrench=T.Wrench(force=T.Vector3(fx, fy, fz),
                            torque=T.Vector3(py * fz - pz * fy, pz * fx - px * fz, px * fy - py * fx)))

    # ---- health -----------------------------------------------------------------------------

    def _health(self, p: dict[str, Any], now: float) -> T.DiagnosticArray | None:
        """The diagnostics of a health payload, or None when it is not yet time for the next
        (``diagnostics_period``) and the daemon's level is the one last published."""
        bridges_in = p.get("bridges")
        if isinstance(bridges_in, dict) and len(bridges_in) > MAX_HEALTH_BRIDGES:
            # a daemon lists every placed bridge and 64 others: more is no skin the views show, and each
            # status costs ~0.5 ms (50 000 took 10 s a message): the first MAX_HEALTH_BRIDGES, counted
            self.malformed += 1
            p = {**p, "bridges": dict(islice(bridges_in.items(), MAX_HEALTH_BRIDGES))}
        s = summarise_health(p)
        source = p["source"] if isinstance(p.get("source"), str) else ""
        links: dict[Any, Any] = p["links"] if isinstance(p.get("links"), dict) else {}
        bridges: dict[Any, Any] = p["bridges"] if isinstance(p.get("bridges"), dict) else {}
        lost_here = sum(self.lost.values())
        lost_new = lost_here - self._lost_published  # since the diagnostics before: a loss is news once
        level, problems = T.DiagnosticStatus.OK, []
        if s["links"] and s["links_up"] < s["links"]:
            level = T.DiagnosticStatus.ERROR
            problems.append(f"{s['links'] - s['links_up']} of {s['links']} links down")
        if s["silent"]:
            level = max(level, T.DiagnosticStatus.WARN)
            problems.append(f"{s['silent']} bridges silent")
        if s["loss"] > LOSS_WARN:
            level = max(level, T.DiagnosticStatus.WARN)
            problems.append(f"{s['loss']:.1%} of frames lost")
        if lost_new > 0:  # (a total that never goes down read WARN for the rest of the week after one hiccup)
            level = max(level, T.DiagnosticStatus.WARN)
            problems.append(f"this bridge to ROS 2 lost {lost_new} daemon messages ({lost_here} in all)")
        if now - self._diagnostics_at < self.diagnostics_period and level == self._diagnostics_level:
            return None
        self._diagnostics_at, self._diagnostics_level = now, level
        self._lost_published = lost_here
        summary = f"{s['alive']} bridges live, {s['links_up']} of {s['links']} links up"
        kv = (lambda d: [T.KeyValue(str(k), _text(v)) for k, v in d.items()])
        status = [T.DiagnosticStatus(
            level=level, name="cellbridge: daemon", hardware_id=source,
            message="; ".join(problems) or summary,
            values=kv({"uptime_s": s["uptime"], "links_up": s["links_up"], "links": s["links"],
                       "bridges_live": s["alive"], "bridges_silent": s["silent"], "frame_loss": s["loss"],
                       "sample_rate_hz": s["rate"], "estimate_ms": s["est_ms"], "estimate_max_ms": s["est_max_ms"],
                       "calibration": s["calibration"], "pub_dropped": s["pub_dropped"],
                       "lost_by_this_subscriber": lost_here}))]
        for name, ln in sorted(links.items(), key=lambda kv_: str(kv_[0])):
            if not isinstance(ln, dict):
                continue
            up = ln.get("connected") is True
            status.append(T.DiagnosticStatus(
                level=T.DiagnosticStatus.OK if up else T.DiagnosticStatus.ERROR, name=f"cellbridge: link {name}",
                hardware_id=source, message="connected" if up else f"down: {_text(ln.get('last_error'))}",
                values=kv({k: ln.get(k) for k in ("url", "bytes", "frames", "crc_errors", "framing_errors",
                                                  "reconnects", "duplicates") if k in ln})))
        for bid, br in sorted(bridges.items(), key=lambda kv_: str(kv_[0])):
            if not isinstance(br, dict):
                continue
            loss = _num(br.get("loss"))
            if br.get("silent") is True:
                lv, msg = T.DiagnosticStatus.ERROR, f"silent for {_num(br.get('age')):.1f} s"
            elif math.isfinite(loss) and loss > LOSS_WARN:
                lv, msg = T.DiagnosticStatus.WARN, f"losing {loss:.1%} of its frames"
            else:
                lv, msg = T.DiagnosticStatus.OK, "live"
            status.append(T.DiagnosticStatus(
                level=lv, name=f"cellbridge: bridge {bid}", hardware_id=source, message=msg,
                values=kv({k: br.get(k) for k in ("link", "sample_rate", "loss", "lost", "frames", "age")
                           if k in br})))
        return T.DiagnosticArray(header=T.Header(stamp=T.stamp(_num(p.get("t_host")))), status=status)

    # ---- markers ----------------------------------------------------------------------------

    def markers(self, t: float) -> T.MarkerArray:
        """The skin's picture at time ``t``: elements coloured by force, contacts, forces, labels."""
        header = T.Header(stamp=T.stamp(t), frame_id=self.frame_id)
        out = [T.Marker(header=header, action=T.Marker.DELETEALL)]
        points, colors = [], []
        for b, (x, y) in sorted(self.layout.items()):
            r = self.readings.get(b, Reading())
            level = min(1.0, max(0.0, r.force / self.force_scale)) if math.isfinite(r.force) else math.nan
            points.append(T.Point(x, y, -0.001))
            colors.append(_rgba(level, 1.0))
        side = self.side * 0.94
        out.append(T.Marker(header=header, ns="elements", id=0, type=T.Marker.CUBE_LIST, action=T.Marker.ADD,
                            scale=T.Vector3(side, side, 0.002), color=T.ColorRGBA(1.0, 1.0, 1.0, 1.0),
                            points=points, colors=colors))
        for c in self.contacts[:MAX_CONTACTS]:  # the views' bound: a picture of 64 contacts at most
            p, n, _ = _place(c)
            if not all(math.isfinite(v) for v in p + n):
                continue
            cid = c["id"] if -INT32 <= c["id"] < INT32 else c["id"] % INT32
            h = T.Header(stamp=header.stamp, frame_id=self.frame_of(c))
            force = _num(c.get("force")) if c.get("valid") is not False else math.nan
            d = _num(c.get("diameter"))
            d = d if math.isfinite(d) and d > 0 else 0.004
            level = min(1.0, max(0.0, force / self.force_scale)) if math.isfinite(force) else math.nan
            out.append(T.Marker(header=h, ns="contacts", id=cid, type=T.Marker.CYLINDER, action=T.Marker.ADD,
                                pose=T.Pose(position=_out(p, n, 0.002), orientation=_z_onto(n)),
                                scale=T.Vector3(d, d, 0.004), color=_rgba(level, 0.9)))
            if math.isfinite(force) and force > 0:
                length = force * ARROW_PER_NEWTON
                out.append(T.Marker(header=h, ns="forces", id=cid, type=T.Marker.ARROW, action=T.Marker.ADD,
                                    points=[_out(p, n, 0.004 + length), _out(p, n, 0.004)],
                                    scale=T.Vector3(0.002, 0.005, 0.004), color=T.ColorRGBA(1.0, 1.0, 1.0, 1.0)))
            out.append(T.Marker(header=h, ns="labels", id=cid, type=T.Marker.TEXT_VIEW_FACING, action=T.Marker.ADD,
                                pose=T.Pose(position=_out(p, n, 0.02)), scale=T.Vector3(0.0, 0.0, 0.008),
                                color=T.ColorRGBA(1.0, 1.0, 1.0, 1.0), text=contact_line(_view_contact(c))))
        return T.MarkerArray(markers=out)


Vec3 = tuple[float, float, float]


def newer_schema(payload: dict[str, Any]) -> bool:
    """Whether ``payload`` says it is of a schema version after :data:`SCHEMA_VERSION`."""
    v = payload.get("v")
    return v.__class__ is int and v > SCHEMA_VERSION


def _place(c: dict[str, Any]) -> tuple[Vec3, Vec3, bool]:
    """A contact's point and outward unit normal in its frame (:meth:`Converter.frame_of`),
    and whether both are known, read as the views read them (:func:`vec3`, :func:`unit3`:
    the Foxglove scene draws the same contact at the same place).

    A contact on a link (``link`` not null: a robot skin) is where its ``position`` and
    ``normal`` say, each NaN when not whole and finite (both when its link names no frame:
    :func:`~cellbridge.tactile.skin_geometry.frame_name`): its ``x``, ``y``
    are its place on the unrolled patches, and +z of a link frame is no direction of its
    skin, so neither stands in. A flat skin's contact (``link`` null or absent) is at
    ``position`` or else ``(x, y, 0)``, along ``normal`` or else +z (its plane's)."""
    p, n = vec3(c.get("position")), unit3(c.get("normal"))
    link = c.get("link")
    if link is not None:
        if frame_name(link) is None:  # in a frame that cannot be named: nothing of it is known here
            return NOWHERE, NOWHERE, False
        return (p if p is not None else NOWHERE, n if n is not None else NOWHERE, p is not None and n is not None)
    return (p if p is not None else (_num(c.get("x")), _num(c.get("y")), 0.0), n if n is not None else UP, True)


def _out(p: tuple[float, float, float], n: tuple[float, float, float], d: float) -> T.Point:
    """The point ``d`` m out of the skin from ``p`` along ``n``."""
    return T.Point(p[0] + d * n[0], p[1] + d * n[1], p[2] + d * n[2])


def _z_onto(n: tuple[float, float, float]) -> T.Quaternion:
    """The rotation that turns +z onto the unit vector ``n`` (a disk marker's axis)."""
    w = 1.0 + n[2]  # (1 + z·n; the half-way quaternion (z × n, 1 + z·n), normalised)
    if w < 1e-9:  # n = -z: half a turn about x
        return T.Quaternion(1.0, 0.0, 0.0, 0.0)
    x, y = -n[1], n[0]
    s = math.sqrt(x * x + y * y + w * w)
    return T.Quaternion(x / s, y / s, 0.0, w / s)


def _rgba(level: float, alpha: float) -> T.ColorRGBA:
    r, g, b = level_rgb(level)
    return T.ColorRGBA(r / 255, g / 255, b / 255, alpha)


def _view_contact(c: dict[str, Any]) -> Contact:
    """The views' contact, for its one-line description."""
    obs = c.get("observable")
    observable = (obs[0] is not False, obs[1] is not False) if isinstance(obs, list) and len(obs) >= 2 else (True, True)
    link, patch = c.get("link"), c.get("patch")  # on a robot: the label says where on it, as the views' do
    return Contact(link=frame_name(link), patch=frame_name(patch),
                   position=vec3(c.get("position")) if link is not None else None,
                   id=int(c["id"]), x=_num(c.get("x")), y=_num(c.get("y")), force=_num(c.get("force")),
                   diameter=_num(c.get("diameter")), observable=observable, valid=c.get("valid") is not False,
                   missed=c["missed"] if isinstance(c.get("missed"), int) else 0,
                   sigma_x=_num(c.get("sigma_x")), sigma_y=_num(c.get("sigma_y")))


def _text(v: Any) -> str:
    """A diagnostic value: numbers as Python writes them, None as empty, strings as they are."""
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)
    return str(v)

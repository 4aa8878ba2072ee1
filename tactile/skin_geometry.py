"""A skin on a robot: patches of elements on surfaces posed in the robot's link frames.

A *patch* is a rows × cols grid of square elements on one surface: a plane, or a
cylinder around a limb (its grid may close on itself around the limb: a *wrap*). It is
posed in a named *link*'s frame, so every element has a centre and an outward normal in
that frame. Patches of one link that lie on one surface (the same plane with the same
in-plane axes, or the same cylinder: axis line and radius) share a *chart*, the
surface unrolled flat: arc length around a cylinder and distance along its axis, or
the plane's own coordinates. The seam between two such patches is then no different
from the seam between two elements of one patch: a press across it is one contact.

Every chart is placed side by side in one flat *atlas*: the skin as the rest of the
system sees it (:class:`~cellbridge.tactile.layout.SkinLayout`, contact estimation, the
emulator's world, the bridges' HELLO positions) is the atlas, and :meth:`SkinGeometry.locate`
takes an atlas position back to its link, patch, 3-D point and normal. A chart that
closes on itself around a cylinder is a *band*: x in ``[x0, x0 + period)`` wraps, and
whatever works on the atlas must treat the band's two ends as neighbours
(:class:`~cellbridge.tactile.seam_estimator.SeamEstimator` for contacts,
:meth:`Band.ghosts` for stimuli).

The description is TOML (:func:`parse_skin`; the daemon's and the emulator's loaders read
the file, and the robot's URDF where it names one). Pure numpy: no I/O here.
"""

from __future__ import annotations

import math
import tomllib
import unicodedata
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Mapping, Sequence

import numpy as np
from cellbridge.tactile.layout import MAX_SIDE, SkinLayout
from numpy.typing import ArrayLike, NDArray

from cellbridge.errors import CellbridgeError

__all__ = [
    "Band", "Chart", "Gateway", "LinkFrame", "MAX_LENGTH", "MAX_NAME", "MAX_PATCHES", "Patch", "SkinError", "SkinGeometry", "SurfacePoint",
    "frame_name", "parse_skin", "pose_matrix", "skin_from_mapping",
]

_DEFAULT_SIDE = 0.040
#: Chart edges in the atlas lie this many element sides apart: no element of one chart is
#: a neighbour of another chart's, and a disk up to this wide off a chart's edge presses
#: nothing of the next chart.
ATLAS_MARGIN = 2.0
#: Two patch poses name one surface when they agree to this (m, and rad for directions).
SAME_SURFACE = 1e-6
#: Bridge ids (as the wire protocol numbers bridges).
MAX_ID = 0xFFFE
#: Characters a link's, patch's or gateway's name may have: a link's name is the frame id of
#: its contacts in ROS 2 and Foxglove, and the views show names whole.
MAX_NAME = 64
#: Patches a description may have: far more than a robot's limbs and faces need, and few
#: enough that finding each patch's surface among the others' stays well under a second.
MAX_PATCHES = 4096
#: m: the farthest an element centre or a link's or patch's origin may lie from its frame's
#: origin along any axis. The views and ROS 2 take a place farther off as unknown
#: (docs/views.md): a description putting anything there is refused here, where the key
#: can be named, instead of published as contacts no subscriber can place.
MAX_LENGTH = 1000.0

_TOP = {"name", "side", "neighbour_gap", "urdf", "link", "patch", "gateway"}
_LINK = {"name", "parent", "origin", "rpy"}
_PATCH = {"name", "link", "shape", "rows", "cols", "pitch", "col_pitch", "radius", "wrap", "origin", "rpy",
          "start", "first_id"}
_GATEWAY = {"name", "patch", "row", "col", "tcp"}


class SkinError(CellbridgeError, ValueError):
    """A skin description that cannot be used; the message names the key and the problem."""


def pose_matrix(origin: Sequence[float] = (0.0, 0.0, 0.0), rpy: Sequence[float] = (0.0, 0.0, 0.0)) -> NDArray[np.float64]:
    """4×4 homogeneous transform of a frame at ``origin`` turned by roll, pitch, yaw about
    the fixed x, y, z axes (the URDF convention: R = Rz(yaw)·Ry(pitch)·Rx(roll))."""
    r, p, y = (float(a) for a in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    m = np.eye(4)
    m[:3, :3] = [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                 [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                 [-sp, cp * sr, cp * cr]]
    m[:3, 3] = [float(v) for v in origin]
    return m


def _frozen(m: NDArray[np.float64]) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in row) for row in np.asarray(m))


@dataclass(frozen=True)
class LinkFrame:
    """A link of the robot: its name, its parent's (None: a root) and its frame's pose in
    the parent's frame at the joints' zero (4×4). ``declared``: False for a link a patch
    names that nothing (no ``[[link]]``, no URDF read) described: its pose is unknown."""

    name: str
    parent: str | None = None
    origin: tuple[tuple[float, ...], ...] = _frozen(np.eye(4))
    declared: bool = True


@dataclass(frozen=True)
class Patch:
    """A grid of elements on one surface in one link's frame.

    Element (row, col) sits at patch coordinates ``(u, v) = start + (col·col_pitch,
    row·pitch)``: on a plane, the point (u, v, 0) of the patch frame, normal +z; on a
    cylinder, the patch frame's z is the axis, u is the arc length from its x axis
    towards y (angle u/radius) and v the distance along z: the point
    (r·cos, r·sin, v), normal outwards. Ids run row-major from ``first_id``."""

    name: str
    link: str
    shape: str  # "plane" | "cylinder"
    rows: int
    cols: int
    pitch: float
    col_pitch: float
    pose: tuple[tuple[float, ...], ...]
    start: tuple[float, float] = (0.0, 0.0)
    radius: float = 0.0
    wrap: bool = False
    first_id: int = 1

    @property
    def n(self) -> int:
        return self.rows * self.cols

    def element_uv(self) -> NDArray[np.float64]:
        """(rows·cols, 2) patch coordinates of the element centres, row-major."""
        r, c = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing="ij")
        return np.stack([self.start[0] + c.ravel() * self.col_pitch, self.start[1] + r.ravel() * self.pitch], axis=1)


@dataclass(frozen=True)
class Gateway:
    """A bridge with a serial line to the host: element (row, col) of ``patch``."""

    name: str
    patch: str
    row: int = 0
    col: int = 0
    tcp: int | None = None


@dataclass(frozen=True)
class Band:
    """A chart that closes on itself: atlas x in ``[x0, x0 + period)`` wraps, for atlas y
    in ``[y0, y1]`` (element centres; the band's elements lie in it and nothing else does)."""

    x0: float
    period: float
    y0: float
    y1: float

    def holds(self, x: ArrayLike, y: ArrayLike, margin: float = 0.0) -> NDArray[np.bool_]:
        """Whether the atlas points lie on the band (``margin`` m of slack on every side)."""
        xa, ya = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        return ((xa >= self.x0 - margin) & (xa < self.x0 + self.period + margin)
                & (ya >= self.y0 - margin) & (ya <= self.y1 + margin))

    def wrap(self, x: float) -> float:
        """``x`` taken into ``[x0, x0 + period)``."""
        return self.x0 + (x - self.x0) % self.period

    def ghosts(self, disks: Sequence[Sequence[float]], side: float) -> list[tuple[float, float, float, float]]:
        """Copies, one period over, of the ``(x, y, force, diameter)`` disks whose footprint
        reaches past an end of the band: what the far end's elements see of a press across
        the wrap seam (the atlas has no element beyond an end, so the original's overhang
        presses nothing)."""
        out = []
        for x, y, f, d in disks:
            reach = 0.5 * d + side
            if not self.holds(x, y, reach):
                continue
            if x - 0.5 * d < self.x0 + side:
                out.append((x + self.period, y, f, d))
            if x + 0.5 * d > self.x0 + self.period - side:
                out.append((x - self.period, y, f, d))
        return out


@dataclass(frozen=True)
class Chart:
    """One surface of one link, unrolled: atlas (x, y) = (x0 + u − u0, y0 + v − v0) in the
    coordinates of ``pose`` (its first patch's frame). ``period``: the circumference when
    the chart closes on itself (else 0). ``width``/``height``: its extent in the atlas."""

    index: int
    link: str
    shape: str
    radius: float
    pose: tuple[tuple[float, ...], ...]
    u0: float
    v0: float
    x0: float
    y0: float
    width: float
    height: float
    period: float
    patches: tuple[str, ...]

    @cached_property
    def _rot_t(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The pose's rotation and translation as arrays (the pose is a tuple: kept, not rebuilt per call)."""
        m = np.asarray(self.pose)
        return m[:3, :3], m[:3, 3]

    def surface(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
        """Points, outward normals and the tangents d/du, d/dv (each (K, 3)) in the link frame."""
        rot, t = self._rot_t
        k = u.shape[0]
        return surface_points(np.full(k, self.shape == "cylinder"), np.full(k, self.shape == "plane"),
                              np.full(k, self.radius), np.broadcast_to(rot, (k, 3, 3)), t, u, v)


def surface_points(cylinder: NDArray[np.bool_], plane: NDArray[np.bool_], radius: NDArray[np.float64],
                   rot: NDArray[np.float64], t: NDArray[np.float64], u: NDArray[np.float64],
                   v: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """Points, outward normals and the tangents d/du, d/dv (each (K, 3)) in the link frame
    of K points (u, v), each on its own chart: ``cylinder``/``plane`` its shape, ``radius``,
    and its pose's rotation (K, 3, 3) and translation ((K, 3) or (3,)). One set of array
    operations for all points, whatever their charts (a frame's contacts lie on many)."""
    k = u.shape[0]
    cyl = cylinder[:, None]
    r = np.where(cylinder, radius, 1.0)
    a = np.where(cylinder, u / r, 0.0)
    ca, sa, zero = np.cos(a), np.sin(a), np.zeros(k)
    local = np.where(cyl, np.stack([r * ca, r * sa, v], axis=1), np.stack([u, v, zero], axis=1))
    nrm = np.where(cyl, np.stack([ca, sa, zero], axis=1), np.array([0.0, 0.0, 1.0]))
    du = np.where(cyl, np.stack([-sa, ca, zero], axis=1), np.array([1.0, 0.0, 0.0]))
    dv = np.where(plane[:, None], np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    out = np.einsum("kij,mkj->mki", rot, np.stack([local, nrm, du, dv]))
    return out[0] + t, out[1], out[2], out[3]


@dataclass(frozen=True)
class SurfacePoint:
    """Where an atlas position is on the robot: link, patch, point and normal in the
    link frame, and the unit tangents along the atlas x and y there (to carry a 2-D
    covariance into the link frame: J·Σ·Jᵀ with J = [tx ty])."""

    link: str
    patch: str
    position: tuple[float, float, float]
    normal: tuple[float, float, float]
    tangent_x: tuple[float, float, float]
    tangent_y: tuple[float, float, float]


@dataclass(frozen=True, eq=False)
class SkinGeometry:
    """A validated skin description: build one with :func:`parse_skin` or
    :func:`skin_from_mapping`. Per-element arrays have one row per element in id order."""

    name: str
    side: float
    neighbour_gap: float
    links: tuple[LinkFrame, ...]
    patches: tuple[Patch, ...]
    gateways: tuple[Gateway, ...]
    charts: tuple[Chart, ...]
    ids: NDArray[np.int64]
    patch_of: NDArray[np.int64]  #: index into ``patches``
    row: NDArray[np.int64]
    col: NDArray[np.int64]
    chart_of: NDArray[np.int64]  #: index into ``charts``
    atlas: NDArray[np.float64]  #: (N, 2) element centres in the atlas
    position: NDArray[np.float64]  #: (N, 3) element centres in their link's frame
    normal: NDArray[np.float64]  #: (N, 3) outward unit normals in their link's frame
    urdf: str | None = None
    _row_of: dict[int, int] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self._row_of.update({int(i): k for k, i in enumerate(self.ids.tolist())})

    @property
    def n(self) -> int:
        return int(self.ids.shape[0])

    @cached_property
    def bands(self) -> tuple[Band, ...]:
        """The charts that close on themselves (built once: a contact job asks for them
        with every read)."""
        return tuple(Band(c.x0, c.period, c.y0, c.y0 + c.height) for c in self.charts if c.period > 0)

    def layout(self) -> SkinLayout:
        """The atlas as a :class:`SkinLayout` (element ids = bridge ids)."""
        return SkinLayout(self.atlas, side=self.side, ids=self.ids, neighbour_gap=self.neighbour_gap)

    @cached_property
    def _patch_by_name(self) -> dict[str, Patch]:
        return {p.name: p for p in self.patches}

    @cached_property
    def _link_by_name(self) -> dict[str, LinkFrame]:
        return {ln.name: ln for ln in self.links}

    def patch(self, name: str) -> Patch:
        try:
            return self._patch_by_name[name]
        except KeyError:
            raise SkinError(f"no patch named {name!r}") from None

    def link(self, name: str) -> LinkFrame:
        try:
            return self._link_by_name[name]
        except KeyError:
            raise SkinError(f"no link named {name!r}") from None

    def element_id(self, patch: str, row: int, col: int) -> int:
        """Bridge id of element (row, col) of ``patch``."""
        p = self.patch(patch)
        if not (0 <= row < p.rows and 0 <= col < p.cols):
            raise SkinError(f"patch {patch!r} has no element ({row}, {col}) (rows 0..{p.rows - 1}, "
                            f"cols 0..{p.cols - 1})")
        return p.first_id + row * p.cols + col

    def gateway_ids(self) -> list[int]:
        return [self.element_id(g.patch, g.row, g.col) for g in self.gateways]

    def row_of(self, element: int) -> int:
        """Row of the per-element arrays holding bridge id ``element`` (KeyError: none)."""
        return self._row_of[int(element)]

    def link_pose(self, name: str) -> NDArray[np.float64]:
        """4×4 pose of link ``name`` in its root link's frame at the joints' zero."""
        m = np.eye(4)
        seen: set[str] = set()
        cur: str | None = name
        while cur is not None and cur not in seen:
            seen.add(cur)
            ln = self.link(cur)
            m = np.asarray(ln.origin) @ m
            cur = ln.parent
        return m

    # -- atlas -> robot -----------------------------------------------------------------
    def chart_at(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.int64]:
        """Index of the chart each atlas point belongs to: the one whose extent is nearest
        (charts lie side by side along x, ``ATLAS_MARGIN`` sides apart)."""
        xa = np.atleast_1d(np.asarray(x, dtype=np.float64))
        lo, hi = self._chart_extents
        dist = np.maximum(np.maximum(lo[None, :] - xa[:, None], xa[:, None] - hi[None, :]), 0.0)
        return np.argmin(dist, axis=1).astype(np.int64)

    # (what locate reads of the charts and elements, built once: a contact message locates
    # every contact of a frame, a hundred frames a second)
    @cached_property
    def _chart_extents(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return np.array([c.x0 for c in self.charts]), np.array([c.x0 + c.width for c in self.charts])

    @cached_property
    def _chart_arrays(self) -> dict[str, NDArray[Any]]:
        """Per chart, as arrays indexed by chart: what :func:`surface_points` and the wrap need."""
        cs = self.charts
        return {"x0": np.array([c.x0 for c in cs]), "period": np.array([c.period for c in cs]),
                "u0": np.array([c.u0 for c in cs]), "y0": np.array([c.y0 for c in cs]),
                "v0": np.array([c.v0 for c in cs]), "radius": np.array([c.radius for c in cs]),
                "cylinder": np.array([c.shape == "cylinder" for c in cs]),
                "plane": np.array([c.shape == "plane" for c in cs]),
                "rot": np.array([np.asarray(c.pose)[:3, :3] for c in cs]).reshape(-1, 3, 3),
                "t": np.array([np.asarray(c.pose)[:3, 3] for c in cs]).reshape(-1, 3)}

    @cached_property
    def _chart_rows(self) -> NDArray[np.int64]:
        """(charts, elements of the largest) each chart's element rows in ascending order,
        padded with -1."""
        counts = np.bincount(self.chart_of, minlength=len(self.charts))
        out = np.full((len(self.charts), max(int(counts.max(initial=0)), 1)), -1, dtype=np.int64)
        for c in range(len(self.charts)):
            sel = np.flatnonzero(self.chart_of == c)
            out[c, :sel.size] = sel
        return out

    @cached_property
    def _atlas_x(self) -> NDArray[np.float64]:
        return np.ascontiguousarray(self.atlas[:, 0])

    @cached_property
    def _atlas_y(self) -> NDArray[np.float64]:
        return np.ascontiguousarray(self.atlas[:, 1])

    @cached_property
    def _patch_names(self) -> list[str]:
        return [p.name for p in self.patches]

    @cached_property
    def _patch_of_list(self) -> list[int]:
        return [int(i) for i in self.patch_of.tolist()]

    def locate(self, x: ArrayLike, y: ArrayLike, chart: ArrayLike | None = None) -> list[SurfacePoint]:
        """Link, patch, point, normal and tangents of atlas points (a position of a
        contact, or of anything else estimated on the atlas). A point off every element
        (in a seam, or a disk centre fitted past a patch's edge) is on its chart's surface,
        extended; its patch is the one of the nearest element of that chart.

        ``chart``: each point's chart index when known (a contact's: its elements'), -1
        where not; a point without one is on the nearest chart. A disk centre fitted past
        a patch's edge, beyond the middle of the margin to the next chart, is nearer that
        chart, on another link: only its elements say which it is on."""
        xa = np.atleast_1d(np.asarray(x, dtype=np.float64))
        ya = np.atleast_1d(np.asarray(y, dtype=np.float64))
        if xa.shape != ya.shape or xa.ndim != 1:
            raise ValueError("x and y must be equal-length 1-D")
        ch = self.chart_at(xa, ya)
        if chart is not None:
            given = np.atleast_1d(np.asarray(chart, dtype=np.int64))
            if given.shape != ch.shape:
                raise ValueError("chart must give one index per point")
            ch = np.where((given >= 0) & (given < len(self.charts)), given, ch)
        ca = self._chart_arrays
        period = ca["period"][ch]
        wraps = period > 0
        x0 = ca["x0"][ch]
        px = np.where(wraps, x0 + np.mod(xa - x0, np.where(wraps, period, 1.0)), xa)
        u = px - x0 + ca["u0"][ch]
        v = ya - ca["y0"][ch] + ca["v0"][ch]
        pts, nrm, du, dv = (a.tolist() for a in surface_points(
            ca["cylinder"][ch], ca["plane"][ch], ca["radius"][ch], ca["rot"][ch], ca["t"][ch], u, v))
        # The nearest element of the point's own chart (the shorter way round a band), the
        # first of equals in the order of rows; among that chart's elements only (a tenth of
        # a humanoid's), -1 where a chart has fewer than the largest one.
        rows = self._chart_rows[ch]
        pad = rows < 0
        at = np.where(pad, 0, rows)
        ddx = np.abs(self._atlas_x[at] - px[:, None])
        ddx = np.where(wraps[:, None], np.minimum(ddx, period[:, None] - ddx), ddx)
        d2 = np.where(pad, np.inf, ddx ** 2 + (self._atlas_y[at] - ya[:, None]) ** 2)
        j = np.argmin(d2, axis=1)
        k = np.arange(j.shape[0])
        # (no element nearer than infinitely far: the first row, as over the whole skin)
        near = np.where(pad[k, j] | (d2[k, j] == np.inf), 0, rows[k, j]).tolist()
        charts, names, patch_of = self.charts, self._patch_names, self._patch_of_list
        return [SurfacePoint(charts[c].link, names[patch_of[e]], tuple(p), tuple(n), tuple(a), tuple(b))
                for c, e, p, n, a, b in zip(ch.tolist(), near, pts, nrm, du, dv)]

    def atlas_of(self, link: str, point: Sequence[float]) -> tuple[float, float, float] | None:
        """Atlas (x, y) of the point of ``link``'s skin nearest a point in the link frame,
        and the point's distance from that surface (m, + outside); None when the link has no
        patch. Of several surfaces of the link, the one whose chart holds the point (within
        a side of its elements' extent) and lies nearest."""
        p = np.asarray(point, dtype=np.float64)
        best: tuple[float, float, float, float] | None = None
        for c in self.charts:
            if c.link != link:
                continue
            m = np.asarray(c.pose)
            local = m[:3, :3].T @ (p - m[:3, 3])
            if c.shape == "cylinder":
                dist = math.hypot(local[0], local[1]) - c.radius
                u = c.radius * math.atan2(local[1], local[0])
                u = c.u0 + (u - c.u0) % (2 * math.pi * c.radius)
                if not c.period and u - c.u0 > c.width + 0.5 * (2 * math.pi * c.radius - c.width):
                    u -= 2 * math.pi * c.radius  # nearer the chart's start than its end
            else:
                dist, u = float(local[2]), float(local[0])
            v = float(local[1] if c.shape == "plane" else local[2])
            x, y = c.x0 + u - c.u0, c.y0 + v - c.v0
            off = max(c.x0 - x, x - c.x0 - c.width, c.y0 - y, y - c.y0 - c.height, 0.0)
            score = abs(dist) + off
            if best is None or score < best[3]:
                best = (x, y, dist, score)
        return None if best is None else (best[0], best[1], best[2])

    def wrap_x(self, x: float, y: float) -> float:
        """``x`` taken into its band (unchanged off every band)."""
        for b in self.bands:
            if bool(b.holds(x, y, self.side)):
                return b.wrap(x)
        return x


# ----------------------------------------------------------------------------- parsing


def _num(value: Any, where: str, lo: float | None = None, strict: bool = False) -> float:
    if type(value) not in (int, float) or not math.isfinite(value):
        raise SkinError(f"{where}: must be a number, got {value!r}")
    if lo is not None and (value < lo or (strict and value == lo)):
        raise SkinError(f"{where}: must be {'>' if strict else '>='} {lo:g}, got {value!r}")
    return float(value)


def _int(value: Any, where: str, lo: int, hi: int) -> int:
    if type(value) is not int or not lo <= value <= hi:
        raise SkinError(f"{where}: must be an integer in {lo}..{hi}, got {value!r}")
    return value


def _vec(value: Any, n: int, where: str, what: str) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != n:
        raise SkinError(f"{where}: must be {what}, got {value!r}")
    return tuple(_num(v, where) for v in value)


def frame_name(value: Any) -> str | None:
    """``value`` when it can name a link, patch or gateway, else None: a string of 1 to
    :data:`MAX_NAME` characters, not all blank, none a control or format character. A
    link's name becomes the ``frame_id`` of its contacts in ROS 2 and Foxglove: a NUL ends
    a string in ROS 2's C++ messages (the frame read there would be another one), and a
    name cut to fit would read as another link's."""
    if (not isinstance(value, str) or not 0 < len(value) <= MAX_NAME or not value.strip()
            or any(unicodedata.category(ch)[0] == "C" for ch in value)):
        return None
    return value


def _name(value: Any, where: str) -> str:
    if frame_name(value) is None:
        raise SkinError(f"{where}: must be a name of 1 to {MAX_NAME} characters, none a control character, "
                        f"got {value!r}")
    return value


def _tables(data: Mapping[str, Any], key: str, source: str) -> list[Mapping[str, Any]]:
    raw = data.get(key, [])
    if not isinstance(raw, list) or not all(isinstance(e, Mapping) for e in raw):
        raise SkinError(f"{source}: '{key}' must be an array of tables ([[{key}]])")
    return raw


def _unknown(keys: Any, allowed: set[str], where: str) -> None:
    extra = sorted(set(keys) - allowed)
    if extra:
        raise SkinError(f"{where}: unknown key '{extra[0]}' (allowed: {', '.join(sorted(allowed))})")


def _pose(e: Mapping[str, Any], where: str) -> NDArray[np.float64]:
    origin = _vec(e["origin"], 3, f"{where}.origin", "[x, y, z] in metres") if "origin" in e else (0.0, 0.0, 0.0)
    if max(abs(v) for v in origin) > MAX_LENGTH:
        raise SkinError(f"{where}.origin: must lie within {MAX_LENGTH:g} m of its frame's origin along every axis "
                        f"(metres), got {list(origin)!r}")
    rpy = _vec(e["rpy"], 3, f"{where}.rpy", "[roll, pitch, yaw] in radians") if "rpy" in e else (0.0, 0.0, 0.0)
    return pose_matrix(origin, rpy)


def _patch(e: Mapping[str, Any], where: str, side: float, gap: float, next_id: int) -> Patch:
    _unknown(e, _PATCH, where)
    for key in ("name", "link", "shape", "rows", "cols"):
        if key not in e:
            raise SkinError(f"{where}: missing key '{key}'")
    name = _name(e["name"], f"{where}.name")
    link = _name(e["link"], f"{where}.link")
    shape = e["shape"]
    if shape not in ("plane", "cylinder"):
        raise SkinError(f"{where}.shape: must be \"plane\" or \"cylinder\", got {shape!r}")
    rows = _int(e["rows"], f"{where}.rows", 1, 10_000)
    cols = _int(e["cols"], f"{where}.cols", 1, 10_000)
    pitch = _num(e.get("pitch", side), f"{where}.pitch", 0.0, True)
    if pitch < side * (1 - 1e-9):
        raise SkinError(f"{where}.pitch: {pitch} m is less than the element side {side} m: elements would overlap")
    radius = 0.0
    wrap = False
    if shape == "cylinder":
        if "radius" not in e:
            raise SkinError(f"{where}: a cylinder patch needs 'radius' (m)")
        radius = _num(e["radius"], f"{where}.radius", 0.0, True)
        if radius > MAX_LENGTH:
            raise SkinError(f"{where}.radius: must be <= {MAX_LENGTH:g} m (metres), got {radius!r}")
        wrap = e.get("wrap", False)
        if type(wrap) is not bool:
            raise SkinError(f"{where}.wrap: must be true or false, got {wrap!r}")
    else:
        for key in ("radius", "wrap"):
            if key in e:
                raise SkinError(f"{where}.{key}: only a cylinder patch has one")
    circ = 2.0 * math.pi * radius
    if wrap:
        if cols < 4:
            raise SkinError(f"{where}.cols: a patch that wraps needs at least 4 columns around, got {cols}")
        col_pitch = circ / cols
        if "col_pitch" in e and not math.isclose(_num(e["col_pitch"], f"{where}.col_pitch"), col_pitch, rel_tol=1e-6):
            raise SkinError(f"{where}.col_pitch: a patch that wraps has col_pitch = 2π·radius/cols = {col_pitch:.6g} m "
                            f"(leave it out)")
    else:
        col_pitch = _num(e.get("col_pitch", pitch), f"{where}.col_pitch", 0.0, True)
    if col_pitch < side * (1 - 1e-9):
        what = f"2π·radius/cols = {col_pitch:.6g} m" if wrap else f"{col_pitch} m"
        raise SkinError(f"{where}: the pitch around ({what}) is less than the element side {side} m: elements "
                        f"would overlap (fewer cols or a larger radius)")
    if shape == "cylinder" and not wrap and cols * col_pitch > circ * (1 + 1e-9):
        raise SkinError(f"{where}: {cols} cols of {col_pitch} m ({cols * col_pitch:.6g} m) go more than once around "
                        f"the cylinder ({circ:.6g} m); a grid that closes on itself is 'wrap = true'")
    # A patch's elements are neighbours (a cell joins each to the next; a press across the
    # seam between two is one contact): a seam wider than neighbour_gap leaves its rows or
    # columns apart, and a wrap whose columns are so far apart closed on nothing (no band).
    for n, step, what, fix in ((rows, pitch, "rows", "a smaller pitch"),
                               (cols, col_pitch, "columns", "more cols or a smaller radius" if wrap
                                else "a smaller col_pitch")):
        if n > 1 and step - side > gap * (1 + 1e-9) + 1e-12:
            raise SkinError(f"{where}: its {what} are {step:.6g} m apart, a seam of {step - side:.6g} m between "
                            f"elements of {side} m, wider than neighbour_gap {gap} m: they would be no neighbours "
                            f"({fix}, or a larger neighbour_gap)")
    start = _vec(e["start"], 2, f"{where}.start", "[u, v] in metres") if "start" in e else (0.0, 0.0)
    first_id = _int(e.get("first_id", next_id), f"{where}.first_id", 1, MAX_ID)
    if first_id + rows * cols - 1 > MAX_ID:
        raise SkinError(f"{where}: ids {first_id}..{first_id + rows * cols - 1} go past the largest bridge id {MAX_ID}")
    return Patch(name, link, shape, rows, cols, pitch, col_pitch, _frozen(_pose(e, where)), (start[0], start[1]),
                 radius, wrap, first_id)


def _links(data: Mapping[str, Any], source: str, urdf_links: Sequence[LinkFrame] | None) -> dict[str, LinkFrame]:
    links: dict[str, LinkFrame] = {ln.name: ln for ln in urdf_links or ()}
    for ln in links.values():  # the URDF's names become frame ids too, its joints' origins link poses
        for name in (ln.name, ln.parent):
            if name is not None and frame_name(name) is None:
                raise SkinError(f"{source}: the URDF's link {name!r} cannot name a frame here (1 to {MAX_NAME} "
                                f"characters, none a control character)")
        m = np.asarray(ln.origin, dtype=np.float64)
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise SkinError(f"{source}: the URDF's link {ln.name!r}: its joint's origin is not finite")
        if np.abs(m[:3, 3]).max() > MAX_LENGTH:
            raise SkinError(f"{source}: the URDF's link {ln.name!r}: its joint's origin must lie within "
                            f"{MAX_LENGTH:g} m of its parent's along every axis, got {m[:3, 3].tolist()!r}")
    for i, e in enumerate(_tables(data, "link", source)):
        where = f"{source}: link[{i}]"
        _unknown(e, _LINK, where)
        if "name" not in e:
            raise SkinError(f"{where}: missing key 'name'")
        name = _name(e["name"], f"{where}.name")
        if name in links:
            raise SkinError(f"{where}.name: link {name!r} is already described"
                            + (" (by the URDF)" if urdf_links and any(ln.name == name for ln in urdf_links) else ""))
        parent = _name(e["parent"], f"{where}.parent") if "parent" in e else None
        links[name] = LinkFrame(name, parent, _frozen(_pose(e, where)))
    for ln in links.values():
        if ln.parent is not None and ln.parent not in links:
            raise SkinError(f"{source}: link {ln.name!r}: parent {ln.parent!r} is not a link of the description")
    # No cycles. Each link is walked up only until a link already known to reach a root:
    # linear in the links, however deep the chain (walking every link to its root took
    # seconds on a chain 10 000 deep).
    rooted: set[str] = set()
    for name in links:
        path: list[str] = []
        on_path: set[str] = set()
        cur: str | None = name
        while cur is not None and cur not in rooted:
            if cur in on_path:
                raise SkinError(f"{source}: link {name!r}: its parents go round in a circle")
            path.append(cur)
            on_path.add(cur)
            cur = links[cur].parent
        rooted.update(path)
    return links


def _same_surface(a: Patch, b: Patch) -> tuple[float, float] | None:
    """(u, v) of b's patch origin in a's patch coordinates when b lies on a's surface with
    its grid aligned (the same plane and in-plane axes; the same cylinder, axis pointing
    the same way), else None."""
    if a.link != b.link or a.shape != b.shape:
        return None
    ma, mb = np.asarray(a.pose), np.asarray(b.pose)
    rel = np.linalg.inv(ma) @ mb
    r, t = rel[:3, :3], rel[:3, 3]
    tol = SAME_SURFACE
    if a.shape == "plane":
        if not (np.allclose(r, np.eye(3), atol=tol) and abs(t[2]) <= tol):
            return None
        return float(t[0]), float(t[1])
    if not math.isclose(a.radius, b.radius, rel_tol=0, abs_tol=tol):
        return None
    if not (np.allclose(r[:, 2], [0.0, 0.0, 1.0], atol=tol) and math.hypot(t[0], t[1]) <= tol):
        return None
    phi = math.atan2(r[1, 0], r[0, 0])  # b's x axis turned about the common axis
    return a.radius * phi, float(t[2])


class _SurfaceKeys:
    """The charts' surfaces so far, as arrays: which charts a patch may lie on, found in one
    vectorised pass over all of them (comparing a patch with every chart in turn, by
    :func:`_same_surface`'s matrix inverse, took minutes for a few thousand patches).

    A chart's key is its first patch's link and shape, its frame's rotation (9 numbers),
    origin, and for a cylinder its radius. A patch on a chart's surface has, within a few
    times :data:`SAME_SURFACE`: a plane, the same rotation and the same offset along the
    normal; a cylinder, the same radius, the same axis, and its origin on that axis. The
    candidates are then confirmed by :func:`_same_surface`, in chart order."""

    _SLACK = 100.0 * SAME_SURFACE  # far looser than _same_surface: never misses a chart it would find

    def __init__(self, most: int) -> None:
        self._links: dict[str, int] = {}
        self._link = np.zeros(most, dtype=np.int64)  # index in _links
        self._shape = np.zeros(most, dtype=np.bool_)  # cylinder
        self._rot = np.zeros((most, 3, 3))
        self._t = np.zeros((most, 3))
        self._radius = np.zeros(most)
        self._n = 0

    def add(self, p: Patch) -> None:
        m = np.asarray(p.pose)
        k = self._n
        self._link[k] = self._links.setdefault(p.link, len(self._links))
        self._shape[k] = p.shape == "cylinder"
        self._rot[k], self._t[k], self._radius[k] = m[:3, :3], m[:3, 3], p.radius
        self._n += 1

    def candidates(self, p: Patch) -> list[int]:
        """Charts whose surface ``p`` may lie on, in chart order."""
        n = self._n
        if n == 0 or p.link not in self._links:
            return []
        m = np.asarray(p.pose)
        rot, t = self._rot[:n], self._t[:n]
        slack = self._SLACK
        d = t - m[:3, 3]  # from p's origin to each chart's
        z = rot[:, :, 2]  # each chart's normal (plane) or axis (cylinder)
        along = np.einsum("ki,ki->k", d, z)
        if p.shape == "plane":
            ok = ~self._shape[:n] & (np.abs(rot - m[:3, :3]).max(axis=(1, 2)) <= slack) & (np.abs(along) <= slack)
        else:
            off_axis = np.linalg.norm(d - along[:, None] * z, axis=1)
            ok = (self._shape[:n] & (np.abs(self._radius[:n] - p.radius) <= slack)
                  & (np.abs(z - m[:3, 2]).max(axis=1) <= slack) & (off_axis <= slack))
        return np.flatnonzero(ok & (self._link[:n] == self._links[p.link])).tolist()


def _check_apart(source: str, side: float, patches: Sequence[Patch], charts: Sequence[Chart],
                 patch_of: NDArray[np.int64], chart_of: NDArray[np.int64], rows: NDArray[np.int64],
                 cols: NDArray[np.int64], position: NDArray[np.float64], normal: NDArray[np.float64]) -> None:
    """Elements of one link on different charts must not lie on top of each other: centres
    closer than half a side, facing the same way (normals less than 90° apart). Two
    patches on surfaces a hair apart (an origin 10 µm off, a turn of 10⁻⁵ rad) are two
    charts, which the layout's overlap check never compares, and every press there read as
    two contacts at one place. Elements at a fold (a box's faces: 0.7 side apart, at 90°)
    or back to back (a plate's two faces) are not on top of each other.

    Only links with several charts are looked at; each element against those in the 27
    grid cells of half a side around it (linear in the elements)."""
    per_link: dict[str, int] = {}
    for c in charts:
        per_link[c.link] = per_link.get(c.link, 0) + 1
    links = {name for name, n in per_link.items() if n > 1}
    if not links:
        return
    cell = 0.5 * side
    grid: dict[tuple[str, int, int, int], list[int]] = {}
    shifts = [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)]
    link_of = [charts[int(c)].link for c in chart_of.tolist()]
    keys = np.floor(position / cell).astype(np.int64).tolist()
    for k in range(len(link_of)):
        link = link_of[k]
        if link not in links:
            continue
        gx, gy, gz = keys[k]
        for dx, dy, dz in shifts:
            for j in grid.get((link, gx + dx, gy + dy, gz + dz), ()):
                if (chart_of[j] != chart_of[k] and float(np.sum((position[j] - position[k]) ** 2)) < cell * cell
                        and float(normal[j] @ normal[k]) > 0.0):
                    a, b = patches[int(patch_of[j])], patches[int(patch_of[k])]
                    gap = float(np.linalg.norm(position[j] - position[k]))
                    raise SkinError(f"{source}: patches {a.name!r} and {b.name!r} of link {link!r} overlap: their "
                                    f"elements ({rows[j]}, {cols[j]}) and ({rows[k]}, {cols[k]}) are {gap:.3g} m "
                                    f"apart, facing the same way (patches of one surface share its pose to "
                                    f"{SAME_SURFACE:g} m and rad)")
        grid.setdefault((link, gx, gy, gz), []).append(k)


def skin_from_mapping(data: Mapping[str, Any], source: str = "skin",
                      urdf_links: Sequence[LinkFrame] | None = None) -> SkinGeometry:
    """Validate a parsed skin description and build its :class:`SkinGeometry`.

    ``urdf_links``: the links of the URDF the description names (``urdf = "robot.urdf"``),
    read by the caller (a loader with file access). Without them a description naming a
    URDF still builds, every link its patches name taken as undeclared
    (:attr:`LinkFrame.declared` False): what the emulator needs, which never asks where a
    link is. Every problem is a :class:`SkinError` naming the key."""
    if not isinstance(data, Mapping):
        raise SkinError(f"{source}: a skin description is a TOML table")
    _unknown(data, _TOP, source)
    name = data.get("name", "")
    if name != "":  # (in every message about the skin, and in topology: a name as a link's)
        name = _name(name, f"{source}: name")
    side = _num(data.get("side", _DEFAULT_SIDE), f"{source}: side", 0.0, True)
    if side > MAX_SIDE:
        raise SkinError(f"{source}: side must be <= {MAX_SIDE:g} m (metres, not millimetres), got {side!r}")
    gap = _num(data.get("neighbour_gap", 0.25 * side), f"{source}: neighbour_gap", 0.0)
    if gap > side:
        raise SkinError(f"{source}: neighbour_gap must be <= the element side {side} m, got {gap!r}")
    urdf = data.get("urdf")
    if urdf is not None and not (isinstance(urdf, str) and urdf):
        raise SkinError(f"{source}: urdf must be a file name, got {urdf!r}")
    links = _links(data, source, urdf_links)

    tables = _tables(data, "patch", source)
    if len(tables) > MAX_PATCHES:
        raise SkinError(f"{source}: patch: at most {MAX_PATCHES} [[patch]] tables, got {len(tables)}")
    patches: list[Patch] = []
    by_name: dict[str, Patch] = {}  # (names looked up in dicts: a skin may have thousands)
    next_id = 1
    for i, e in enumerate(tables):
        where = f"{source}: patch[{i}]" + (f" ({e['name']})" if isinstance(e.get("name"), str) else "")
        p = _patch(e, where, side, gap, next_id)
        if p.name in by_name:
            raise SkinError(f"{where}.name: duplicate patch name {p.name!r}")
        by_name[p.name] = p
        if p.link not in links:
            if urdf is None or urdf_links is not None:
                known = ", ".join(sorted(links)) or "none"
                raise SkinError(f"{where}.link: no link {p.link!r} (links: {known})")
            links[p.link] = LinkFrame(p.link, declared=False)
        patches.append(p)
        next_id = p.first_id + p.n
    if not patches:
        raise SkinError(f"{source}: no [[patch]] in the description")
    spans = sorted((p.first_id, p.first_id + p.n - 1, p.name) for p in patches)
    for (a0, a1, an), (b0, b1, bn) in zip(spans, spans[1:]):
        if b0 <= a1:
            raise SkinError(f"{source}: patches {an!r} (ids {a0}..{a1}) and {bn!r} (ids {b0}..{b1}) share ids")

    # charts: patches of one link on one surface
    chart_of_patch: list[int] = []
    offsets: list[tuple[float, float]] = []
    refs: list[int] = []  # first patch of each chart
    keys = _SurfaceKeys(len(patches))
    for k, p in enumerate(patches):
        for c in keys.candidates(p):
            off = _same_surface(patches[refs[c]], p)
            if off is not None:
                chart_of_patch.append(c)
                offsets.append(off)
                break
        else:
            chart_of_patch.append(len(refs))
            offsets.append((0.0, 0.0))
            refs.append(k)
            keys.add(p)

    ids_l, patch_l, row_l, col_l, chart_l, u_l, v_l = [], [], [], [], [], [], []
    for k, p in enumerate(patches):
        uv = p.element_uv()
        r, cc = np.divmod(np.arange(p.n), p.cols)
        ids_l.append(p.first_id + np.arange(p.n))
        patch_l.append(np.full(p.n, k))
        row_l.append(r)
        col_l.append(cc)
        chart_l.append(np.full(p.n, chart_of_patch[k]))
        u_l.append(uv[:, 0] + offsets[k][0])
        v_l.append(uv[:, 1] + offsets[k][1])
    ids = np.concatenate(ids_l).astype(np.int64)
    patch_of = np.concatenate(patch_l).astype(np.int64)
    rows = np.concatenate(row_l).astype(np.int64)
    cols = np.concatenate(col_l).astype(np.int64)
    chart_of = np.concatenate(chart_l).astype(np.int64)
    u = np.concatenate(u_l)
    v = np.concatenate(v_l)

    charts: list[Chart] = []
    atlas = np.empty((ids.size, 2))
    x_next = 0.0
    for c, ref in enumerate(refs):
        rp = patches[ref]
        sel = np.flatnonzero(chart_of == c)
        cu, cv = u[sel], v[sel]
        period = 0.0
        if rp.shape == "cylinder":
            circ = 2.0 * math.pi * rp.radius
            cu = np.mod(cu, circ)
            cols_u = np.unique(np.round(cu, 9))
            gaps = np.diff(np.concatenate([cols_u, [cols_u[0] + circ]]))
            widest = int(np.argmax(gaps))
            if gaps[widest] <= side + gap + 1e-12:  # closes on itself: cut before the first patch's column 0
                period = circ
                cut = float(np.mod(rp.start[0] - 0.5 * rp.col_pitch, circ))
            else:  # an open arc: cut in its widest gap
                cut = float(np.mod(cols_u[widest] + 0.5 * gaps[widest], circ))
            cu = np.mod(cu - cut, circ) + cut  # every element on one turn from the cut
            u[sel] = cu
            u_lo = cut if period else float(cu.min()) - 0.5 * side
        else:
            u_lo = float(cu.min()) - 0.5 * side
        v_lo = float(cv.min()) - 0.5 * side
        width = period if period else float(cu.max()) + 0.5 * side - u_lo
        height = float(cv.max()) + 0.5 * side - v_lo
        atlas[sel, 0] = x_next + (cu - u_lo)
        atlas[sel, 1] = cv - v_lo
        names = tuple(dict.fromkeys(patches[int(k)].name for k in np.unique(patch_of[sel]).tolist()))
        charts.append(Chart(c, rp.link, rp.shape, rp.radius, rp.pose, u_lo, v_lo, x_next, 0.0, width, height,
                            period, names))
        x_next += width + ATLAS_MARGIN * side

    order = np.argsort(ids, kind="stable")
    ids, patch_of, rows, cols, chart_of = ids[order], patch_of[order], rows[order], cols[order], chart_of[order]
    atlas, u, v = atlas[order], u[order], v[order]
    position = np.empty((ids.size, 3))
    normal = np.empty((ids.size, 3))
    for c, ch in enumerate(charts):
        sel = np.flatnonzero(chart_of == c)
        pts, nrm, _, _ = ch.surface(u[sel], v[sel])
        position[sel] = pts
        normal[sel] = nrm

    _check_apart(source, side, patches, charts, patch_of, chart_of, rows, cols, position, normal)
    far = np.flatnonzero(np.abs(position).max(axis=1) > MAX_LENGTH)
    if far.size:  # (the first in id order)
        k = int(far[0])
        p = patches[int(patch_of[k])]
        i = patches.index(p)
        raise SkinError(f"{source}: patch[{i}] ({p.name}): element ({int(rows[k])}, {int(cols[k])}) lies at "
                        f"({', '.join(f'{v:.6g}' for v in position[k])}) m in link {p.link!r}'s frame: every "
                        f"coordinate must be within {MAX_LENGTH:g} m")

    gateways: list[Gateway] = []
    gw_ids: dict[int, str] = {}
    gw_names: set[str] = set()
    tcp_of: dict[int, str] = {}
    for i, e in enumerate(_tables(data, "gateway", source)):
        where = f"{source}: gateway[{i}]"
        _unknown(e, _GATEWAY, where)
        for key in ("name", "patch"):
            if key not in e:
                raise SkinError(f"{where}: missing key '{key}'")
        gname = _name(e["name"], f"{where}.name")
        if gname in gw_names:
            raise SkinError(f"{where}.name: duplicate gateway name {gname!r}")
        gw_names.add(gname)
        pname = _name(e["patch"], f"{where}.patch")
        if pname not in by_name:
            raise SkinError(f"{where}.patch: no patch {pname!r}")
        p = by_name[pname]
        row = _int(e.get("row", 0), f"{where}.row", 0, p.rows - 1)
        col = _int(e.get("col", 0), f"{where}.col", 0, p.cols - 1)
        tcp = _int(e["tcp"], f"{where}.tcp", 0, 65535) if "tcp" in e else None
        if tcp:  # (0: any free port, as many as wanted) `mesh up --tcp` serves one gateway a port
            if tcp in tcp_of:
                raise SkinError(f"{where}.tcp: port {tcp} is already gateway {tcp_of[tcp]!r}'s")
            tcp_of[tcp] = gname
        bid = p.first_id + row * p.cols + col
        if bid in gw_ids:
            raise SkinError(f"{where}: element ({row}, {col}) of {pname!r} is already gateway {gw_ids[bid]!r}")
        gw_ids[bid] = gname
        gateways.append(Gateway(gname, pname, row, col, tcp))
    if not gateways:
        raise SkinError(f"{source}: no [[gateway]]: a skin needs at least one bridge with a line to the host")

    skin = SkinGeometry(name, side, gap, tuple(links.values()), tuple(patches), tuple(gateways), tuple(charts),
                        ids, patch_of, rows, cols, chart_of, atlas, position, normal, urdf)
    try:
        skin.layout()  # elements of one chart must not overlap
    except ValueError as exc:
        raise SkinError(f"{source}: {exc} (patches on one surface of one link share its coordinates)") from None
    return skin


def parse_skin(text: str, source: str = "skin", urdf_links: Sequence[LinkFrame] | None = None) -> SkinGeometry:
    """A skin description from the text of its TOML file (metres and radians throughout).

    Takes text, not a path: this layer does no I/O (the daemon's and the emulator's loaders
    read the file, and the URDF it names). Every problem is a :class:`SkinError` naming the
    key. The format::

        name = "arm"            # optional
        side = 0.040            # element side (m), every patch
        neighbour_gap = 0.010   # optional: widest seam between neighbours (default side/4); a
                                # patch's pitches are at most side + neighbour_gap
        urdf = "arm.urdf"       # optional: link frames from the robot's URDF

        [[link]]                # links the URDF does not hold (all of them, without one)
        name = "forearm"
        parent = "upper_arm"    # optional
        origin = [0.0, 0.0, 0.30]   # optional: its frame in the parent's (m)
        rpy = [0.0, 0.0, 0.0]       # optional (rad; roll, pitch, yaw about fixed x, y, z)

        [[patch]]
        name = "forearm"
        link = "forearm"
        shape = "cylinder"      # or "plane"
        radius = 0.045          # cylinder only (m)
        wrap = true             # cylinder only: the grid closes on itself around the limb
        rows = 4                # along the axis (plane: along y)
        cols = 7                # around the axis (plane: along x); >= 4 when it wraps
        pitch = 0.040           # optional: between rows (default side)
        col_pitch = 0.040       # optional: between cols (default pitch; 2π·radius/cols when it wraps)
        origin = [0.0, 0.0, 0.05]   # the patch frame in the link's: a cylinder's axis is its z,
        rpy = [0.0, 0.0, 0.0]       # angle 0 its x
        start = [0.0, 0.02]     # optional: (u, v) of element (0, 0)'s centre (cylinder: arc length, z)
        first_id = 1            # optional: bridge id of element (0, 0), row-major (default: after the last patch)
                                # (at most MAX_PATCHES = 4096 patches)

        [[gateway]]
        name = "arm"
        patch = "forearm"
        row = 0                 # optional: which element's bridge has the serial line
        col = 0
        tcp = 0                 # optional: its TCP port with `mesh up --tcp`

    Patches of one link on one surface (the same plane with the same in-plane axes; the
    same cylinder with its axis the same way) share its coordinates, and a press across
    their seam is one contact. Origins, radii and element centres lie within
    :data:`MAX_LENGTH` (1 km) of their frame's origin along every axis.
    """
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SkinError(f"{source}: not valid TOML: {exc}") from None
    except RecursionError:
        raise SkinError(f"{source}: not valid TOML: nested too deeply") from None
    return skin_from_mapping(data, source, urdf_links)


def is_skin_description(data: Mapping[str, Any]) -> bool:
    """Whether a parsed TOML document is a skin description (it has patches) rather than a
    mesh or layout file."""
    return "patch" in data

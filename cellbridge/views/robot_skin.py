"""The skin on the robot as the views read it: links, patches and element frames.

The daemon's ``topology`` carries, with a skin description, a ``skin`` map (links with
their pose in the parent's frame, patches with their grid, each element's patch,
row, column, centre and normal in its link's frame: docs/zmq-api.md). :func:`read_skin`
turns that map into a :class:`RobotSkin`, defensively: every field is untrusted, a
value of the wrong type or out of range (NaN, ±inf, a pose that is no rigid motion,
an element in no patch) is left out and counted in :attr:`RobotSkin.bad`, never
raised; sizes are bounded (:data:`MAX_LINKS`, :data:`MAX_PATCHES`, ``max_elements``).
:func:`pack_patches` places the patches' grids side by side for the flat views (the
page and the terminal draw the skin patch by patch); :func:`rigid` and the quaternion
helpers give Foxglove its frame transforms and the orientation of what it draws.

Sans-I/O and numpy-free on purpose: it runs on every message of a view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

MAX_LINKS = 64  #: links kept of a skin description (the rest counted in ``bad``)
MAX_PATCHES = 256  #: patches kept
MAX_NAME = 64  #: characters of a link's or patch's name kept (a longer one is cut)
MAX_PATCH_SIDE = 128  #: rows or columns of one patch (more: the patch is not drawn as a grid)
MAX_LENGTH = 1e3  #: m: a coordinate further from its frame's origin is unknown
ORTHO_TOLERANCE = 1e-3  #: how far a pose's rotation may be from orthonormal and still be taken


def _num(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return math.nan
    return float(value)


def _int(value: Any, lo: int, hi: int) -> int | None:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        return None
    return value


def _name(value: Any) -> str | None:
    """A name (cut to :data:`MAX_NAME`), or None when it is not a non-empty string."""
    if not isinstance(value, str) or not value:
        return None
    return value[:MAX_NAME]


def vec3(value: Any, limit: float = MAX_LENGTH) -> tuple[float, float, float] | None:
    """Three finite numbers each within ±``limit``, or None."""
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        return None
    out = tuple(_num(v) for v in value)
    if not all(-limit <= v <= limit for v in out):  # False for NaN
        return None
    return out  # type: ignore[return-value]  # three of them


def unit3(value: Any) -> tuple[float, float, float] | None:
    """A unit vector from three numbers (normalised; None when not a direction)."""
    v = vec3(value, 1e6)
    if v is None:
        return None
    n = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
    if not (1e-9 < n < math.inf):
        return None
    return (v[0] / n, v[1] / n, v[2] / n)


Quat = tuple[float, float, float, float]  # (x, y, z, w)


def rigid(value: Any) -> tuple[tuple[float, float, float], Quat] | None:
    """(translation, rotation quaternion x y z w) of a 4×4 pose given as rows, or None
    when it is not one: not 4×4 numbers, not finite, a translation beyond
    :data:`MAX_LENGTH`, a rotation that is not orthonormal with determinant +1 (within
    :data:`ORTHO_TOLERANCE`) or a last row other than (0, 0, 0, 1)."""
    if not isinstance(value, (list, tuple)) or len(value) != 4:
        return None
    rows = []
    for r in value:
        if not isinstance(r, (list, tuple)) or len(r) != 4:
            return None
        row = [_num(v) for v in r]
        if not all(math.isfinite(v) for v in row):
            return None
        rows.append(row)
    if any(abs(a - b) > ORTHO_TOLERANCE for a, b in zip(rows[3], (0.0, 0.0, 0.0, 1.0))):
        return None
    t = (rows[0][3], rows[1][3], rows[2][3])
    if not all(abs(v) <= MAX_LENGTH for v in t):
        return None
    m = [row[:3] for row in rows[:3]]
    for i in range(3):
        for j in range(3):
            dot = sum(m[k][i] * m[k][j] for k in range(3))
            if abs(dot - (1.0 if i == j else 0.0)) > ORTHO_TOLERANCE:
                return None
    det = (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
           + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]))
    if det <= 0:
        return None
    return t, quat_of_matrix(m)


def quat_of_matrix(m: list[list[float]]) -> Quat:
    """The unit quaternion (x, y, z, w) of a rotation matrix (rows), by the largest of
    its four squared components (well conditioned for every rotation)."""
    tr = m[0][0] + m[1][1] + m[2][2]
    if tr > 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = ((m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s, 0.25 * s)
    elif m[0][0] > m[1][1] and m[0][0] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[0][0] - m[1][1] - m[2][2])
        q = (0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s, (m[2][1] - m[1][2]) / s)
    elif m[1][1] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[1][1] - m[0][0] - m[2][2])
        q = ((m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s, (m[0][2] - m[2][0]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2][2] - m[0][0] - m[1][1])
        q = ((m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s, (m[1][0] - m[0][1]) / s)
    n = math.sqrt(sum(c * c for c in q))
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def quat_from_to(a: tuple[float, float, float], b: tuple[float, float, float]) -> Quat:
    """The shortest rotation taking unit vector ``a`` to unit vector ``b`` (x, y, z, w)."""
    d = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    c = (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])
    q = (c[0], c[1], c[2], 1.0 + d)
    n = math.sqrt(sum(x * x for x in q))
    if n < 1e-12:  # opposite: half a turn about any axis perpendicular to a
        axis = (0.0, -a[2], a[1]) if abs(a[0]) < 0.9 else (-a[1], a[0], 0.0)
        n = math.sqrt(sum(x * x for x in axis))
        return (axis[0] / n, axis[1] / n, axis[2] / n, 0.0)
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def rotate(q: Quat, v: tuple[float, float, float]) -> tuple[float, float, float]:
    """``v`` rotated by unit quaternion ``q`` (x, y, z, w)."""
    x, y, z, w = q
    # v + 2w(q×v) + 2 q×(q×v)
    cx, cy, cz = y * v[2] - z * v[1], z * v[0] - x * v[2], x * v[1] - y * v[0]
    ccx, ccy, ccz = y * cz - z * cy, z * cx - x * cz, x * cy - y * cx
    return (v[0] + 2 * (w * cx + ccx), v[1] + 2 * (w * cy + ccy), v[2] + 2 * (w * cz + ccz))


@dataclass
class SkinLink:
    name: str
    parent: str | None
    pose: tuple[tuple[float, float, float], Quat] | None  # in the parent's frame; None: unknown


@dataclass
class SkinPatch:
    name: str
    link: str | None
    shape: str  # "plane", "cylinder" or "?"
    rows: int
    cols: int
    wrap: bool
    pitch: float  # m between rows (NaN: unknown)
    col_pitch: float  # m between columns along the surface (NaN: unknown)
    ids: list[int] = field(default_factory=list)  # its elements, in the order heard


@dataclass
class ElementPlace:
    """Where an element is: its patch's grid place, and its centre and normal in the link frame."""

    patch: str
    row: int
    col: int
    position: tuple[float, float, float] | None
    normal: tuple[float, float, float] | None


@dataclass
class RobotSkin:
    name: str
    links: dict[str, SkinLink]
    patches: dict[str, SkinPatch]
    elements: dict[int, ElementPlace]
    bad: int = 0  #: fields left out as unreadable (wrong type, out of range, beyond the limits)

    def link_of(self, bridge: int) -> str | None:
        e = self.elements.get(bridge)
        p = self.patches.get(e.patch) if e is not None else None
        return p.link if p is not None else None


def _list(d: dict[str, Any], key: str) -> list[Any]:
    v = d.get(key)
    return v if isinstance(v, list) else []


def read_skin(value: Any, max_elements: int, max_bridge: int = 0xFFFF) -> RobotSkin | None:
    """The ``skin`` map of a ``topology`` payload as a :class:`RobotSkin`; None when there
    is none (``null``, absent, not a map: a flat skin). Never raises on any value."""
    if not isinstance(value, dict):
        return None
    bad = 0
    links: dict[str, SkinLink] = {}
    raw_links = _list(value, "links")
    for ln in raw_links[:MAX_LINKS]:
        name = _name(ln.get("name")) if isinstance(ln, dict) else None
        if name is None or name in links:
            bad += 1
            continue
        parent = ln.get("parent")
        pose = rigid(ln.get("origin"))
        if parent is not None and _name(parent) is None:
            pose = None  # a parent not named: where the link is is not known (it is no root)
        if pose is None:
            bad += 1
        links[name] = SkinLink(name, _name(parent), pose)
    bad += max(0, len(raw_links) - MAX_LINKS)
    bad += sum(1 for ln in links.values() if ln.parent is not None and ln.parent not in links)  # a parent unheard of
    patches: dict[str, SkinPatch] = {}
    raw_patches = _list(value, "patches")
    for p in raw_patches[:MAX_PATCHES]:
        name = _name(p.get("name")) if isinstance(p, dict) else None
        if name is None or name in patches:
            bad += 1
            continue
        rows, cols = _int(p.get("rows"), 1, MAX_PATCH_SIDE), _int(p.get("cols"), 1, MAX_PATCH_SIDE)
        shape = p.get("shape")
        pitch, col_pitch = _num(p.get("pitch")), _num(p.get("col_pitch"))
        link = _name(p.get("link"))
        if rows is None or cols is None or link is None:
            bad += 1
        patches[name] = SkinPatch(name, link, shape if shape in ("plane", "cylinder") else "?", rows or 0, cols or 0,
                                  p.get("wrap") is True,
                                  pitch if 0 < pitch <= MAX_LENGTH else math.nan,
                                  col_pitch if 0 < col_pitch <= MAX_LENGTH else math.nan)
    bad += max(0, len(raw_patches) - MAX_PATCHES)
    elements: dict[int, ElementPlace] = {}
    el = value.get("elements")
    if isinstance(el, dict):
        ids = _list(el, "ids")
        n = min(len(ids), 65536)
        cols_ = [(_list(el, k)[:n] + [None] * n)[:n] for k in ("patch", "row", "col", "position", "normal")]
        for b, pname, row, col, pos, nrm in zip(ids[:n], *cols_):
            bridge = _int(b, 0, max_bridge)
            patch = patches.get(pname) if isinstance(pname, str) else None
            if bridge is None or patch is None or bridge in elements:
                bad += 1
                continue
            r, c = _int(row, 0, max(0, patch.rows - 1)), _int(col, 0, max(0, patch.cols - 1))
            if r is None or c is None or patch.rows == 0:
                bad += 1
                continue
            if len(elements) >= max_elements:
                bad += 1
                continue
            position, normal = vec3(pos), unit3(nrm)
            if position is None or normal is None:
                bad += 1
            elements[bridge] = ElementPlace(patch.name, r, c, position, normal)
            patch.ids.append(bridge)
        bad += max(0, len(ids) - n)
    elif el is not None:
        bad += 1
    name = value.get("name")
    return RobotSkin(_name(name) or "", links, patches, elements, bad)


@dataclass
class PatchBlock:
    """Where a patch's grid goes on the flat views' grid: its element (row 0, col 0)
    at grid (``row0``, ``col0``) (rows grow upwards, as the layout's y), its title in
    grid row ``row0 + rows``."""

    name: str
    link: str | None
    rows: int
    cols: int
    row0: int
    col0: int
    wrap: bool
    title: str = ""  # "link / name" as shown (the views' model sets it, its strings escaped)
    short: str = ""  # the name alone, for a block too narrow for the title


def pack_patches(patches: list[SkinPatch], gap: int = 1) -> tuple[list[PatchBlock], int, int]:
    """The patches' grids side by side, in order, in bands no wider than about 1.5 times
    the square root of their area (the widest patch at least), a title row above each and
    ``gap`` blank cells between them; (blocks, rows, cols) of the whole."""
    shown = [p for p in patches if p.rows > 0 and p.cols > 0]
    if not shown:
        return [], 0, 0
    area = sum((p.rows + 1) * (p.cols + gap) for p in shown)
    width = max(max(p.cols for p in shown), math.ceil(1.5 * math.sqrt(area)))
    bands: list[list[SkinPatch]] = [[]]
    used = 0
    for p in shown:
        need = p.cols if not bands[-1] else used + gap + p.cols
        if bands[-1] and need > width:
            bands.append([])
            need = p.cols
        bands[-1].append(p)
        used = need
    heights = [max(p.rows for p in band) + 1 for band in bands]
    total_rows = sum(heights) + gap * (len(bands) - 1)
    cols = 0
    blocks = []
    top = total_rows  # the first band at the top
    for band, h in zip(bands, heights):
        x = 0
        for p in band:
            blocks.append(PatchBlock(p.name, p.link, p.rows, p.cols, row0=top - 1 - p.rows, col0=x, wrap=p.wrap))
            x += p.cols + gap
        cols = max(cols, x - gap)
        top -= h + gap
    return blocks, total_rows, cols

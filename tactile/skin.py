"""The skin as an array of elements: layout, contact geometry and the array's response.

A skin is a mosaic of square elements. Each element only reports two capacitances, so
everything finer than an element — where a contact sits, how big it is when it
straddles a seam — has to come from how a contact's footprint is shared between the
elements it lies on. This module is that sharing, exactly:

* :class:`SkinLayout` — element centres, side and ids, loaded from a grid spec or a
  TOML layout file, with neighbours derived from the geometry (never listed by hand,
  so they cannot disagree with the positions);
* :func:`disk_rect_overlap` — the exact area of a disk lying on an axis-aligned
  rectangle, closed form and vectorised (a straddling contact's share of each element);
* :func:`skin_response` — (ΔC1, ΔC2) of every element for several simultaneous disk
  contacts, under the paper's assumptions (uniform pressure F/S, no sheet tension) or
  with an optional membrane-tension spread (a 2-D Gaussian blur of the pressure field,
  paper §III.A).

Units are SI throughout (m, N, Pa, F).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Literal, Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellbridge.tactile.element import ElementParams, sensitivity

__all__ = [
    "SkinLayout",
    "grid_layout",
    "parse_layout",
    "layout_from_mapping",
    "layout_to_toml",
    "disk_rect_overlap",
    "disk_element_overlap",
    "as_contacts",
    "skin_response",
    "disk_response",
    "pressure_field",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

_DEFAULT_SIDE = ElementParams().side

#: Most elements one layout may hold: far beyond any robot skin, far below what would
#: exhaust memory before a typo (``rows = 1000000000``) is reported.
MAX_ELEMENTS = 1_000_000
#: Largest element side (m): far beyond any element, far below a side in millimetres
#: written where metres are expected.
MAX_SIDE = 1.0
#: Farthest an element centre may lie from the origin, in element sides. Beyond about
#: 4.5e6 sides float64 cannot resolve an element's edges to the 1e-9·side the overlap
#: check works to, and two elements at the same place would pass it.
MAX_REACH = 1e5
_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


def _checked(value: Any, name: str, kind: type[int] | type[float], minimum: float | None = None) -> Any:
    """``value`` as a plain int or float, or ValueError naming ``name``.

    The one conversion used for layout arguments and layout files: it refuses what
    ``int()``/``float()`` would silently coerce (``True``, ``"0.04"``, ``1.7`` as an
    id) or fail on with another exception (``inf`` as a count).
    """
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    if kind is float:
        ok = ok or isinstance(value, (float, np.floating))
        if ok and not math.isfinite(value):
            raise ValueError(f"{name} must be a finite number, got {value!r}")
        what = "a number"
    else:
        what = "an integer"
    if not ok:
        raise ValueError(f"{name} must be {what}, got {value!r}")
    out = kind(value)
    if kind is int and not _INT64_MIN <= out <= _INT64_MAX:
        raise ValueError(f"{name} must be an integer in [-2**63, 2**63), got {value!r}")
    if minimum is not None and out < minimum:
        raise ValueError(f"{name} must be >= {minimum:g}, got {value!r}")
    return out


def _as_ids(raw: ArrayLike, what: str) -> IntArray:
    """Integer ids as int64, or ValueError: never truncated (0.5 → 0) nor wrapped
    (2**63 as uint64 → −2**63)."""
    a = np.asarray(raw)
    if a.dtype.kind == "i":
        ok = True
    elif a.dtype.kind == "u":
        ok = bool(np.all(a <= _INT64_MAX))
    elif a.dtype.kind == "f":
        with np.errstate(invalid="ignore"):
            ok = bool(np.all((a == np.round(a)) & (a >= -(2.0**63)) & (a < 2.0**63)))
    else:
        ok = False
    if not ok:
        raise ValueError(f"{what} must be integers in [-2**63, 2**63)")
    return a.astype(np.int64)


# --------------------------------------------------------------------------- layout


@dataclass(frozen=True, eq=False)
class SkinLayout:
    """Where the elements of one skin are: centres (N×2, m), common side (m), ids.

    Elements are axis-aligned squares of edge ``side`` centred on ``centres``. They
    may leave gaps (seams) between them but must not overlap, because every point of
    the skin belongs to at most one element's capacitor. ``ids`` are the numbers the
    rest of the system uses for an element (typically its bridge id); row ``i`` of
    every per-element array in :mod:`cellbridge.tactile` is element ``ids[i]``.

    ``neighbour_gap`` is how wide a seam may be for two elements to still count as
    neighbours: a contact cannot fall into a wider gap and press both.
    """

    centres: FloatArray
    side: float = _DEFAULT_SIDE
    ids: IntArray = field(default=None)  # type: ignore[assignment]
    neighbour_gap: float | None = None

    def __post_init__(self) -> None:
        c = np.asarray(self.centres, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != 2:
            raise ValueError(f"centres must have shape (N, 2), got {c.shape}")
        if c.shape[0] == 0:
            raise ValueError("a layout needs at least one element")
        if c.shape[0] > MAX_ELEMENTS:
            raise ValueError(f"a layout holds at most {MAX_ELEMENTS} elements, got {c.shape[0]}")
        if not np.all(np.isfinite(c)):
            raise ValueError("element centres must be finite")
        side = _checked(self.side, "element side", float)
        if not 0 < side <= MAX_SIDE:
            raise ValueError(
                f"element side must be > 0 and <= {MAX_SIDE:g} m, got {self.side!r} "
                "(metres expected, not millimetres)"
            )
        reach = MAX_REACH * side
        if np.abs(c).max() > reach:
            raise ValueError(
                f"element centres must lie within {reach:g} m ({MAX_REACH:g} element sides) "
                f"of the origin, got {float(np.abs(c).max()):g} m: farther, float64 cannot "
                "resolve the elements' edges"
            )
        n = c.shape[0]
        if self.ids is None:
            ids = np.arange(n, dtype=np.int64)
        else:
            if np.shape(self.ids) != (n,):
                raise ValueError(f"ids must have shape ({n},), got {np.shape(self.ids)}")
            ids = _as_ids(self.ids, "element ids")
        if np.unique(ids).size != n:
            raise ValueError("element ids must be unique")
        gap = 0.25 * side if self.neighbour_gap is None else _checked(
            self.neighbour_gap, "neighbour_gap", float, minimum=0.0)
        if gap > side:
            # Wider seams than an element: no contact presses both sides, and the
            # neighbour search would compare (gap/side)² candidates per element.
            raise ValueError(f"neighbour_gap must be <= the element side {side:g} m, got {gap!r}")
        object.__setattr__(self, "centres", _readonly(c))
        object.__setattr__(self, "side", side)
        object.__setattr__(self, "ids", _readonly(ids))
        object.__setattr__(self, "neighbour_gap", gap)
        self._check_no_overlap()

    # -- geometry -------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of elements."""
        return int(self.centres.shape[0])

    def __len__(self) -> int:
        return self.n

    @cached_property
    def bounds(self) -> FloatArray:
        """(N, 4) rectangles ``[x0, y0, x1, y1]`` of the elements (m)."""
        h = 0.5 * self.side
        b = np.concatenate([self.centres - h, self.centres + h], axis=1)
        return _readonly(b)

    @cached_property
    def extent(self) -> tuple[float, float, float, float]:
        """Bounding box ``(x0, y0, x1, y1)`` of the whole skin (m)."""
        b = self.bounds
        return (float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max()))

    @cached_property
    def _near_pairs(self) -> IntArray:
        """(P, 2) pairs ``i < j`` whose squares come within ``neighbour_gap``, at least.

        A spatial hash: with cells of side + gap, two such squares lie in the same or
        adjacent cells, so only the 3×3 cells around each element are compared —
        O(N) for a skin instead of all N² pairs (30 000 elements in well under a
        second instead of 44 s). Sorted by (i, j).
        """
        h = self.side + self.neighbour_gap
        cell = np.floor((self.centres - self.centres.min(axis=0)) / h).astype(np.int64)
        width = int(cell[:, 1].max()) + 3
        key = (cell[:, 0] + 1) * width + (cell[:, 1] + 1)
        order = np.argsort(key, kind="stable")
        skey = key[order]
        out = []
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                target = key + dx * width + dy
                lo = np.searchsorted(skey, target, side="left")
                cnt = np.searchsorted(skey, target, side="right") - lo
                i = np.repeat(np.arange(self.n), cnt)
                first = np.repeat(lo - (np.cumsum(cnt) - cnt), cnt)
                j = order[np.arange(i.size) + first]
                keep = i < j
                out.append(np.stack([i[keep], j[keep]], axis=1))
        pairs = np.concatenate(out, axis=0)
        return _readonly(pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))])

    def _pair_gaps(self) -> tuple[FloatArray, FloatArray]:
        # Signed gaps between the near pairs' rectangles along x and y: > 0 is a seam
        # of that width, < 0 is the length over which the two overlap in that coordinate.
        b = self.bounds
        bi = b[self._near_pairs[:, 0]]
        bj = b[self._near_pairs[:, 1]]
        gx = np.maximum(bj[:, 0] - bi[:, 2], bi[:, 0] - bj[:, 2])
        gy = np.maximum(bj[:, 1] - bi[:, 3], bi[:, 1] - bj[:, 3])
        return gx, gy

    def _check_no_overlap(self) -> None:
        eps = 1e-9 * self.side
        gx, gy = self._pair_gaps()
        bad = np.nonzero((gx < -eps) & (gy < -eps))[0]
        if bad.size:
            i, j = self._near_pairs[bad[0]]
            raise ValueError(
                f"elements {self.ids[i]} and {self.ids[j]} overlap; elements of a "
                "skin must not overlap"
            )

    def _edges(self, connectivity: str) -> IntArray:
        if connectivity not in ("edge", "corner"):
            raise ValueError(f"connectivity must be 'edge' or 'corner', got {connectivity!r}")
        share = 1e-6 * self.side  # a shared border must be longer than this
        gx, gy = self._pair_gaps()
        close_x = gx <= self.neighbour_gap
        close_y = gy <= self.neighbour_gap
        if connectivity == "edge":
            adj = (close_x & (gy < -share)) | (close_y & (gx < -share))
        else:
            adj = close_x & close_y
        return self._near_pairs[adj].astype(np.int64)

    @cached_property
    def edges(self) -> IntArray:
        """(E, 2) index pairs ``i < j`` of elements sharing a border (across a seam ≤ gap).

        Edge neighbours, not corner ones: a single convex contact that presses two
        diagonal elements also presses one of the elements between them, while two
        separate contacts on diagonal elements must stay two contacts.
        """
        return _readonly(self._edges("edge"))

    @cached_property
    def corner_edges(self) -> IntArray:
        """(E, 2) pairs that touch at least at a corner (8-neighbourhood on a grid)."""
        return _readonly(self._edges("corner"))

    def adjacency(self, connectivity: Literal["edge", "corner"] = "edge") -> NDArray[np.bool_]:
        """Dense (N, N) symmetric neighbour matrix, for small skins and inspection."""
        e = self.edges if connectivity == "edge" else self.corner_edges
        a = np.zeros((self.n, self.n), dtype=bool)
        a[e[:, 0], e[:, 1]] = True
        a[e[:, 1], e[:, 0]] = True
        return a

    def neighbours(self, index: int, connectivity: Literal["edge", "corner"] = "edge") -> IntArray:
        """Indices (not ids) of the neighbours of element ``index``."""
        if not (isinstance(index, (int, np.integer)) and not isinstance(index, (bool, np.bool_))
                and 0 <= index < self.n):
            raise ValueError(f"element index must be an integer in 0..{self.n - 1}, got {index!r}")
        e = self.edges if connectivity == "edge" else self.corner_edges
        return np.sort(np.concatenate([e[e[:, 0] == index, 1], e[e[:, 1] == index, 0]]))

    def index_of(self, ids: ArrayLike) -> IntArray:
        """Row indices of the given element ids; ValueError for an unknown id."""
        want = np.atleast_1d(_as_ids(ids, "element ids"))
        order = np.argsort(self.ids)
        pos = np.searchsorted(self.ids, want, sorter=order)
        pos = np.clip(pos, 0, self.n - 1)
        idx = order[pos]
        miss = self.ids[idx] != want
        if miss.any():
            raise ValueError(f"unknown element id {int(want[miss][0])}")
        return idx

    def element_at(self, points: ArrayLike) -> IntArray:
        """Index of the element under each point (…, 2), or -1 in a seam or off the skin.

        A point on a shared border goes to the element with the lower index.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.shape[-1:] != (2,):
            raise ValueError(f"points must have shape (..., 2), got {p.shape}")
        flat = p.reshape(-1, 2)
        b = self.bounds
        inside = (
            (flat[:, None, 0] >= b[None, :, 0])
            & (flat[:, None, 0] <= b[None, :, 2])
            & (flat[:, None, 1] >= b[None, :, 1])
            & (flat[:, None, 1] <= b[None, :, 3])
        )
        idx = np.where(inside.any(axis=1), inside.argmax(axis=1), -1)
        return idx.reshape(p.shape[:-1]).astype(np.int64)


def grid_layout(
    rows: int,
    cols: int,
    pitch: float = _DEFAULT_SIDE,
    side: float | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
    first_id: int = 0,
    *,
    neighbour_gap: float | None = None,
    where: str = "",
) -> SkinLayout:
    """A rows × cols grid; element (r, c) is centred at ``origin + (c·pitch, r·pitch)``.

    Ids run row-major from ``first_id``. ``side`` defaults to the pitch (no seams).
    ``where`` prefixes the argument names in error messages (a layout file's keys).
    """
    rows = _checked(rows, f"{where}rows", int, minimum=1)
    cols = _checked(cols, f"{where}cols", int, minimum=1)
    first_id = _checked(first_id, f"{where}first_id", int)
    pitch = _checked(pitch, f"{where}pitch", float)
    if not pitch > 0:
        raise ValueError(f"{where}pitch must be > 0 m, got {pitch!r}")
    side = pitch if side is None else _checked(side, f"{where}side", float)
    if side > pitch * (1 + 1e-12):
        raise ValueError(f"{where}side {side} m exceeds the pitch {pitch} m: elements would overlap")
    if not (isinstance(origin, (list, tuple)) and len(origin) == 2):
        raise ValueError(f"{where}origin must be [x, y] in metres, got {origin!r}")
    ox, oy = (_checked(v, f"{where}origin", float) for v in origin)
    if rows * cols > MAX_ELEMENTS:
        raise ValueError(
            f"{where}rows × {where}cols = {rows * cols} elements, more than a layout holds "
            f"({MAX_ELEMENTS})"
        )
    if first_id + rows * cols - 1 > _INT64_MAX:
        raise ValueError(f"{where}first_id {first_id} + {rows * cols} elements overflows 64-bit ids")
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    centres = np.stack([ox + c.ravel() * pitch, oy + r.ravel() * pitch], axis=1)
    ids = first_id + np.arange(centres.shape[0], dtype=np.int64)
    return SkinLayout(centres, side=side, ids=ids, neighbour_gap=neighbour_gap)


def _table(doc: Mapping[str, Any], known: set[str], where: str) -> None:
    if not isinstance(doc, Mapping):
        raise ValueError(f"{where.rstrip('.') or 'the layout'} must be a table, got {doc!r}")
    unknown = set(doc) - known
    if unknown:
        raise ValueError(f"unknown keys {where}{sorted(unknown)} (known: {sorted(known)})")


def layout_from_mapping(data: Mapping[str, Any], source: str = "layout") -> SkinLayout:
    """Build a layout from a parsed layout document (see :func:`parse_layout`).

    Every problem is a ``ValueError`` that starts with ``source`` and names the key.
    """
    try:
        return _layout_from_mapping(data)
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}") from None


def _layout_from_mapping(data: Mapping[str, Any]) -> SkinLayout:
    _table(data, {"side", "neighbour_gap", "grid", "element"}, "")
    if ("grid" in data) == ("element" in data):
        raise ValueError("a layout needs exactly one of [grid] or [[element]]")
    gap = data.get("neighbour_gap")
    gap = None if gap is None else _checked(gap, "neighbour_gap", float, minimum=0.0)
    side = data.get("side")
    side = None if side is None else _checked(side, "side", float)
    if "grid" in data:
        g = data["grid"]
        _table(g, {"rows", "cols", "pitch", "side", "origin", "first_id"}, "[grid].")
        if "rows" not in g or "cols" not in g:
            raise ValueError("[grid] needs rows and cols")
        return grid_layout(
            g["rows"], g["cols"], pitch=g.get("pitch", _DEFAULT_SIDE), side=g.get("side", side),
            origin=g.get("origin", (0.0, 0.0)), first_id=g.get("first_id", 0),
            neighbour_gap=gap, where="[grid].",
        )
    elems = data["element"]
    if not isinstance(elems, list) or not elems:
        raise ValueError("[[element]] must be a non-empty array of tables")
    ids = np.empty(len(elems), dtype=np.int64)
    xy = np.empty((len(elems), 2))
    for k, e in enumerate(elems):
        where = f"[[element]] #{k}."
        _table(e, {"id", "x", "y"}, where)
        for key in ("id", "x", "y"):
            if key not in e:
                raise ValueError(f"{where}{key} is missing (each element needs id, x and y in metres)")
        ids[k] = _checked(e["id"], f"{where}id", int)
        xy[k] = (_checked(e["x"], f"{where}x", float), _checked(e["y"], f"{where}y", float))
    return SkinLayout(xy, side=_DEFAULT_SIDE if side is None else side, ids=ids, neighbour_gap=gap)


def parse_layout(text: str, source: str = "layout") -> SkinLayout:
    """Build a skin layout from the text of a TOML layout file (metres throughout).

    Takes text, not a path, so this layer stays free of I/O;
    ``cellbridge.daemon.layout_file.load_layout`` reads the file. Every problem is a
    ``ValueError`` that starts with ``source`` and names the key
    (``arm.toml: [grid].rows must be an integer, got inf``). Types are
    strict: counts and ids are TOML integers, lengths are numbers (an integer is
    fine), never booleans or strings.

    Either a grid::

        side = 0.040            # optional, defaults to the pitch
        [grid]
        rows = 2
        cols = 2
        pitch = 0.040
        origin = [0.0, 0.0]     # centre of element (row 0, col 0)
        first_id = 0            # ids row-major from here

    or a list of elements (any arrangement, e.g. following a robot's limb)::

        side = 0.040
        neighbour_gap = 0.010   # optional: widest seam between neighbours
        [[element]]
        id = 17
        x = 0.000
        y = 0.000
    """
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{source}: not valid TOML: {exc}") from None
    except RecursionError:  # tomllib parses nested arrays and tables recursively
        raise ValueError(f"{source}: not valid TOML: nested too deeply") from None
    return layout_from_mapping(data, source)


def layout_to_toml(layout: SkinLayout) -> str:
    """The ``[[element]]`` form of a layout, readable by :func:`parse_layout`."""
    lines = [f"side = {layout.side!r}", f"neighbour_gap = {layout.neighbour_gap!r}", ""]
    for i in range(layout.n):
        lines += [
            "[[element]]",
            f"id = {int(layout.ids[i])}",
            f"x = {float(layout.centres[i, 0])!r}",
            f"y = {float(layout.centres[i, 1])!r}",
            "",
        ]
    return "\n".join(lines)


# ----------------------------------------------------------- disk ∩ rectangle, exact


def _prim(t: FloatArray, root: FloatArray) -> FloatArray:
    # ∫₀ᵗ √(1−x²) dx for t ∈ [−1, 1], given root = √(1−t²).
    return 0.5 * (t * root + np.arcsin(t))


def _quadrant(a: FloatArray, b: FloatArray) -> FloatArray:
    """Area of the unit disk with x > a and y > b, any a and b.

    Over x, the chord {y > b} has length √(1−x²) − b where the line y = b cuts the
    circle (|x| < c = √(1−b²)), and either 0 (b ≥ 0) or the whole chord 2√(1−x²)
    (b < 0) outside. Integrating from a to 1 with P(t) = ∫₀ᵗ√(1−x²)dx and
    x1 = clip(a, −c, c):

    * b ≥ 0:  U = P(c) − P(x1) − b·(c − x1)
    * b < 0:  U = π/2 − 2P(a) − P(c) + P(x1) − b·(c − x1)
    """
    a = np.clip(a, -1.0, 1.0)
    b = np.clip(b, -1.0, 1.0)
    c = np.sqrt(1.0 - b * b)
    x1 = np.clip(a, -c, c)
    pc = _prim(c, np.abs(b))
    px1 = _prim(x1, np.sqrt(np.maximum(1.0 - x1 * x1, 0.0)))
    common = pc - px1 - b * (c - x1)
    pa = _prim(a, np.sqrt(1.0 - a * a))
    return np.where(b >= 0.0, common, 0.5 * np.pi - 2.0 * pa - pc + px1 - b * (c - x1))


def disk_rect_overlap(
    cx: ArrayLike,
    cy: ArrayLike,
    r: ArrayLike,
    x0: ArrayLike,
    y0: ArrayLike,
    x1: ArrayLike,
    y1: ArrayLike,
) -> FloatArray:
    """Exact area (m²) of the disk (centre cx, cy; radius r) lying on [x0,x1]×[y0,y1].

    Closed form: by inclusion–exclusion over the rectangle's four corners, the area is
    a signed sum of "disk beyond a corner" areas, each the integral of a clipped
    circular chord (``∫√(r²−x²)dx`` in closed form). Everything broadcasts, so M
    disks against N rectangles is one call with (M, 1) and (1, N) arguments. Radius 0
    gives 0. Accurate to a few ulp of ``r²``.
    """
    cx, cy, r, x0, y0, x1, y1 = (np.asarray(v, dtype=np.float64) for v in (cx, cy, r, x0, y0, x1, y1))
    if np.any(r < 0) or np.any(~np.isfinite(r)):
        raise ValueError("disk radius must be finite and >= 0")
    if np.any(x1 < x0) or np.any(y1 < y0):
        raise ValueError("rectangle must have x1 >= x0 and y1 >= y0")
    pos = r > 0
    rs = np.where(pos, r, 1.0)
    ax0 = (x0 - cx) / rs
    ax1 = (x1 - cx) / rs
    by0 = (y0 - cy) / rs
    by1 = (y1 - cy) / rs
    # The four corners in one vectorised call (these arrays are often small, and
    # numpy's per-call overhead would otherwise dominate).
    a4, b4 = np.broadcast_arrays(np.stack(np.broadcast_arrays(ax0, ax1, ax0, ax1)),
                                 np.stack(np.broadcast_arrays(by0, by0, by1, by1)))
    q = _quadrant(a4, b4)
    u = q[0] - q[1] - q[2] + q[3]
    rect = (x1 - x0) * (y1 - y0)
    with np.errstate(over="ignore", invalid="ignore"):  # r² beyond float range
        area = u * rs * rs
        # Clamp rounding: never negative, never more than the disk or the rectangle.
        area = np.clip(area, 0.0, np.minimum(np.pi * rs * rs, rect))
    # A rectangle whose farthest corner lies in the disk is wholly inside: its own
    # area, exactly. The corner terms above cancel to nothing when the disk is much
    # larger than the rectangle (r = 1e5 m: 0.08 % short; 1e8 m: 0).
    far = np.hypot(np.maximum(np.abs(x0 - cx), np.abs(x1 - cx)),
                   np.maximum(np.abs(y0 - cy), np.abs(y1 - cy)))
    area = np.where(far <= r, rect, area)
    return np.where(pos, area, 0.0)


def disk_element_overlap(layout: SkinLayout, centres: ArrayLike, radii: ArrayLike) -> FloatArray:
    """(M, N) area of each of M disks lying on each of the N elements (m²)."""
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    if r.shape[0] != c.shape[0]:
        raise ValueError(f"{c.shape[0]} centres but {r.shape[0]} radii")
    b = layout.bounds
    return disk_rect_overlap(
        c[:, :1], c[:, 1:2], r[:, None], b[None, :, 0], b[None, :, 1], b[None, :, 2], b[None, :, 3]
    )


# ----------------------------------------------------------------- contact response


def as_contacts(contacts: ArrayLike) -> FloatArray:
    """Validate contacts as an (M, 4) array of ``(x, y, force, diameter)`` rows.

    A single contact may be given as a flat 4-sequence; an empty list is no contact.
    """
    c = np.asarray(contacts, dtype=np.float64)
    if c.size == 0:
        return np.zeros((0, 4))
    if c.ndim == 1:
        c = c[None, :]
    if c.ndim != 2 or c.shape[1] != 4:
        raise ValueError(f"contacts must be (x, y, force, diameter) rows, got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("contacts must be finite")
    if np.any(c[:, 2] < 0):
        raise ValueError("contact force must be >= 0 N")
    if np.any(c[:, 3] <= 0):
        raise ValueError("contact diameter must be > 0 m")
    return c


def _i0e(x: FloatArray) -> FloatArray:
    # exp(−x)·I0(x) for x >= 0 without overflow: numpy's i0 below 500, the
    # asymptotic series (error < 1e-12 there) above.
    out = np.empty_like(x)
    small = x < 500.0
    xs = x[small]
    out[small] = np.i0(xs) * np.exp(-xs)
    xl = x[~small]
    t = 1.0 / (8.0 * xl)
    out[~small] = (1.0 + t * (1.0 + t * (4.5 + t * 37.5))) / np.sqrt(2.0 * np.pi * xl)
    return out


_GL_R = np.polynomial.legendre.leggauss(24)


def _disk_blur(rho: FloatArray, radius: FloatArray, s: float) -> FloatArray:
    """Indicator of a disk convolved with an isotropic 2-D Gaussian (std s), at distance ρ.

    In polar coordinates around the disk centre the angular integral is a Bessel
    function: Φ(ρ) = ∫₀ᴿ (r/s²)·exp(−(r−ρ)²/2s²)·i0e(rρ/s²) dr. The integrand is
    negligible (< e⁻³²) beyond |r − ρ| > 8s, and a 24-point Gauss–Legendre rule over
    that window is accurate to ~1e-14.
    """
    lo = np.maximum(rho - 8.0 * s, 0.0)
    hi = np.minimum(rho + 8.0 * s, radius)
    ok = hi > lo
    t, w = _GL_R
    mid = 0.5 * (hi + lo)
    half = np.where(ok, 0.5 * (hi - lo), 0.0)
    r = mid[..., None] + half[..., None] * t
    rr = rho[..., None]
    f = (r / (s * s)) * np.exp(-0.5 * ((r - rr) / s) ** 2) * _i0e(r * rr / (s * s))
    return np.clip((f * w).sum(axis=-1) * half, 0.0, 1.0)


@dataclass(frozen=True)
class _Nodes:
    xy: FloatArray  # (P, 2) quadrature points
    w: FloatArray  # (P,) weights (m²)
    elem: IntArray  # (P,) element index of each point


_NODE_CACHE: dict[tuple[bytes, int], _Nodes] = {}


def _element_nodes(bounds: FloatArray, q: int) -> _Nodes:
    # Tensor-product Gauss rule on q×q sub-cells per element, 2×2 points per cell:
    # fourth-order accurate for the smooth (blurred) integrand.
    key = (bounds.tobytes(), q)
    hit = _NODE_CACHE.get(key)
    if hit is not None:
        return hit
    g = 0.5 + 0.5 * np.array([-1.0, 1.0]) / math.sqrt(3.0)
    u = ((np.arange(q)[:, None] + g[None, :]) / q).ravel()  # in (0, 1)
    ux, uy = np.meshgrid(u, u, indexing="ij")
    wx = bounds[:, 2] - bounds[:, 0]
    wy = bounds[:, 3] - bounds[:, 1]
    x = bounds[:, None, 0] + ux.ravel()[None, :] * wx[:, None]
    y = bounds[:, None, 1] + uy.ravel()[None, :] * wy[:, None]
    xy = np.stack([x.ravel(), y.ravel()], axis=1)
    w = np.repeat(wx * wy / (4.0 * q * q), u.size * u.size)
    elem = np.repeat(np.arange(bounds.shape[0]), u.size * u.size)
    nodes = _Nodes(xy, w, elem)
    if len(_NODE_CACHE) > 64:
        _NODE_CACHE.clear()
    _NODE_CACHE[key] = nodes
    return nodes


def _spread_cells(side: float, spread: float, quad_step: float | None) -> int:
    step = 0.5 * spread if quad_step is None else float(quad_step)
    if not (math.isfinite(step) and step > 0):
        raise ValueError(f"quad_step must be > 0 m, got {quad_step!r}")
    return int(min(max(math.ceil(side / step), 4), 256))


def pressure_field(
    points: ArrayLike, contacts: ArrayLike, spread: float = 0.0
) -> FloatArray:
    """Pressure (Pa) at ``points`` (…, 2) from disk contacts, after the tension spread.

    ``spread = 0`` is eq. 1: F/S inside each disk, 0 outside. ``spread = s > 0`` blurs
    that field with a normalised 2-D Gaussian of standard deviation s (per axis), which
    keeps each contact's total force but spreads it beyond the footprint.
    """
    c = as_contacts(contacts)
    p = np.asarray(points, dtype=np.float64)
    if p.shape[-1:] != (2,):
        raise ValueError(f"points must have shape (..., 2), got {p.shape}")
    s = _check_spread(spread)
    flat = p.reshape(-1, 2)
    out = np.zeros(flat.shape[0])
    for x, y, f, d in c:
        rad = 0.5 * d
        sigma = f / (math.pi * rad * rad)
        rho = np.hypot(flat[:, 0] - x, flat[:, 1] - y)
        if s == 0.0:
            out += np.where(rho <= rad, sigma, 0.0)
        else:
            grid, prof = _disk_profile(rad, s)
            out += sigma * np.interp(rho, grid, prof, left=prof[0], right=0.0)
    return out.reshape(p.shape[:-1])


#: Smallest non-zero spread (m): below it the blurred rim is narrower than float64
#: resolves at a contact's radius, and the profile table collapses.
MIN_SPREAD = 1e-9


def _check_spread(spread: float) -> float:
    s = float(spread)
    if not (math.isfinite(s) and s >= 0):
        raise ValueError(f"spread must be finite and >= 0 m, got {spread!r}")
    if 0 < s < MIN_SPREAD:
        raise ValueError(
            f"spread must be 0 or >= {MIN_SPREAD:g} m (a sub-nanometre blur is none), got {spread!r}"
        )
    return s


def disk_response(
    layout: SkinLayout,
    contacts: ArrayLike,
    params: ElementParams | None = None,
    spread: float = 0.0,
    quad_step: float | None = None,
) -> tuple[FloatArray, FloatArray]:
    """(M, N) ΔC1 and ΔC2 of every element for each contact *on its own*.

    Without spread, responses of separate (non-overlapping) disks add, so
    :func:`skin_response` is the column sum of this. With spread they do not (the
    foams are nonlinear in the summed pressure); this is then what each contact would
    do alone, which is what a one-disk fit needs for many candidate disks at once.
    """
    return _disk_response(layout.bounds, layout.side, as_contacts(contacts), params, spread, quad_step)


def _disk_response(
    bounds: FloatArray,
    side: float,
    c: FloatArray,
    params: ElementParams | None,
    spread: float,
    quad_step: float | None,
) -> tuple[FloatArray, FloatArray]:
    # Per-disk responses on the elements ``bounds`` (any subset of a layout).
    s = _check_spread(spread)
    m, n = c.shape[0], bounds.shape[0]
    if m == 0:
        return np.zeros((0, n)), np.zeros((0, n))
    rad = 0.5 * c[:, 3]
    sigma = c[:, 2] / (math.pi * rad * rad)
    if s == 0.0:
        g1, g2 = sensitivity(sigma, params)
        a = disk_rect_overlap(
            c[:, :1], c[:, 1:2], rad[:, None],
            bounds[None, :, 0], bounds[None, :, 1], bounds[None, :, 2], bounds[None, :, 3],
        )
        return a * g1[:, None], a * g2[:, None]
    nodes = _element_nodes(bounds, _spread_cells(side, s, quad_step))
    out1 = np.zeros((m, n))
    out2 = np.zeros((m, n))
    for k in range(m):  # per contact: only the nodes it can reach are evaluated
        p = _disk_g_on_nodes(nodes, c[k], s, params)
        if p is None:
            continue
        idx, g1, g2 = p
        out1[k] = np.bincount(nodes.elem[idx], weights=g1 * nodes.w[idx], minlength=n)
        out2[k] = np.bincount(nodes.elem[idx], weights=g2 * nodes.w[idx], minlength=n)
    return out1, out2


_PROFILE_STEPS_PER_S = 40


_PROFILE_CACHE: dict[tuple[float, float], tuple[FloatArray, FloatArray]] = {}


def _disk_profile(radius: float, s: float) -> tuple[FloatArray, FloatArray]:
    """Φ(ρ) of :func:`_disk_blur` tabulated every s/40 over the disk's blurred rim.

    The profile is smooth on the scale s, so linear interpolation in this table is
    accurate to ~2e-5 and costs one Bessel quadrature per table point instead of one
    per quadrature node of the elements. Profiles are cached by (R, s): a fit
    evaluates many disks of the same size at different places.
    """
    key = (float(radius), float(s))
    hit = _PROFILE_CACHE.get(key)
    if hit is not None:
        return hit
    lo = max(radius - 8.0 * s, 0.0)
    hi = radius + 8.0 * s
    n = int(math.ceil((hi - lo) / s * _PROFILE_STEPS_PER_S)) + 1
    rho = np.linspace(lo, hi, n)
    out = (rho, _disk_blur(rho, np.full(n, radius), s))
    if len(_PROFILE_CACHE) >= 256:
        _PROFILE_CACHE.clear()
    _PROFILE_CACHE[key] = out
    return out


def _near_nodes(nodes: _Nodes, x: float, y: float, reach: float) -> tuple[IntArray, FloatArray]:
    dx = nodes.xy[:, 0] - x
    dy = nodes.xy[:, 1] - y
    idx = np.nonzero((np.abs(dx) < reach) & (np.abs(dy) < reach))[0]
    return idx, np.hypot(dx[idx], dy[idx])


def _profile_near(
    nodes: _Nodes, contact: FloatArray, s: float
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray, float] | None:
    """Nodes a blurred disk reaches, their distance to its centre, the disk's radial
    profile and its nominal pressure; None when the contact touches no node."""
    x, y, f, d = contact
    rad = 0.5 * d
    if f == 0.0:
        return None
    idx, rho = _near_nodes(nodes, x, y, rad + 8.0 * s)
    if idx.size == 0:
        return None
    grid, prof = _disk_profile(rad, s)
    return idx, rho, grid, prof, f / (math.pi * rad * rad)


def _blurred_on_nodes(nodes: _Nodes, contact: FloatArray, s: float) -> tuple[IntArray, FloatArray] | None:
    near = _profile_near(nodes, contact, s)
    if near is None:
        return None
    idx, rho, grid, prof, sigma = near
    return idx, sigma * np.interp(rho, grid, prof, left=prof[0], right=0.0)


def _disk_g_on_nodes(
    nodes: _Nodes, contact: FloatArray, s: float, params: ElementParams | None
) -> tuple[IntArray, FloatArray, FloatArray] | None:
    # One contact alone: g_n(σ·Φ(ρ)) is itself a smooth function of ρ, so it is
    # tabulated on the profile grid and interpolated, instead of solving eq. 2 at
    # every node.
    near = _profile_near(nodes, contact, s)
    if near is None:
        return None
    idx, rho, grid, prof, sigma = near
    g1t, g2t = sensitivity(sigma * prof, params)
    g1 = np.interp(rho, grid, g1t, left=g1t[0], right=0.0)
    g2 = np.interp(rho, grid, g2t, left=g2t[0], right=0.0)
    return idx, g1, g2


def skin_response(
    layout: SkinLayout,
    contacts: ArrayLike,
    params: ElementParams | None = None,
    spread: float = 0.0,
    quad_step: float | None = None,
) -> tuple[FloatArray, FloatArray]:
    """(ΔC1, ΔC2) in farads of every element, shape (N,), for simultaneous disk contacts.

    ``contacts`` are ``(x, y, force, diameter)`` rows (m, m, N, m); the disks must not
    overlap one another. With ``spread = 0`` (the paper's assumption) each element sees
    the exact part of each disk lying on it at that disk's pressure F/S, and parts add:
    ``ΔC_n,i = Σ_j A_ij·g_n(F_j/S_j)``. Force that lands in a seam or off the skin is
    simply not measured.

    ``spread = s > 0`` models the tension of the conductive sheets (paper §III.A,
    Fig. 5): the pressure field of all contacts is summed and blurred with a 2-D
    Gaussian of standard deviation s (force conserved), and eqs. 2–3 are applied
    point by point, ``ΔC_n,i = ∫_element g_n(σ_blurred(x, y)) dA``, integrated with a
    2×2-point Gauss rule on cells of ``quad_step`` (default s/2). The paper's eq. 4
    writes the same bell as exp(−x²/s_paper²), i.e. s_paper = √2·s.
    """
    c = as_contacts(contacts)
    s = _check_spread(spread)
    if c.shape[0] == 0:
        return np.zeros(layout.n), np.zeros(layout.n)
    if s == 0.0:
        d1, d2 = disk_response(layout, c, params)
        return d1.sum(axis=0), d2.sum(axis=0)
    nodes = _element_nodes(layout.bounds, _spread_cells(layout.side, s, quad_step))
    press = np.zeros(nodes.xy.shape[0])
    for k in range(c.shape[0]):
        p = _blurred_on_nodes(nodes, c[k], s)
        if p is not None:
            press[p[0]] += p[1]
    g1, g2 = sensitivity(press, params)
    return (
        np.bincount(nodes.elem, weights=g1 * nodes.w, minlength=layout.n),
        np.bincount(nodes.elem, weights=g2 * nodes.w, minlength=layout.n),
    )

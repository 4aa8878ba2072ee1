"""The skin as a mosaic of elements: :class:`SkinLayout` (centres, side, ids) loaded from
a grid spec or a TOML layout file, with neighbours derived from the geometry (never listed
by hand, so they cannot disagree with the positions). Units are SI (m)."""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Literal, Mapping

import numpy as np
from cellbridge.tactile.arrays import FloatArray, IntArray
from cellbridge.tactile.element import ElementParams
from numpy.typing import ArrayLike, NDArray

__all__ = ["SkinLayout", "grid_layout", "layout_from_mapping", "layout_to_toml", "parse_layout"]


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
    ids: IntArray = field(default=None)  # type: ignore[arg-type]  # None: __post_init__ numbers the elements
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
        assert self.neighbour_gap is not None  # resolved by __post_init__
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
        assert self.neighbour_gap is not None  # resolved by __post_init__
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
    ``cellbridge.daemon.shell.layout_file.load_layout`` reads the file. Every problem is a
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

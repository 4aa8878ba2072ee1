"""Mesh files: which bridges touch which cells, where their elements are, who is a gateway.

A mesh is a bipartite graph: cells are shared broadcast media, bridges touch one or
more cells, and one or more bridges are gateways with a serial line to the host. Two
bridges *hear* each other when they share a cell. The file format (TOML)::

    loss = 0.0          # default probability that one delivery is lost
    ber = 0.0           # default bit-error rate of one delivery
    side = 0.04         # element side (m)
    bitrate = 1000000   # cell bit rate (bit/s)

    [[cell]]
    id = 1
    loss = 0.01         # optional: overrides the default for deliveries over this cell

    [[bridge]]
    id = 1
    cells = [1]
    position = [0.0, 0.0]   # element centre (m)
    gateway = true          # optional, default false
    tcp = 0                 # optional: the TCP port of this gateway's stream with `mesh up --tcp`
                            # (0 or absent: any free port; without --tcp, none)

    [[link]]            # optional per-edge overrides between two bridges
    a = 1
    b = 2
    loss = 0.05
    ber = 1e-6

    [[wrap]]            # optional: a band of the skin that closes on itself (a cylinder's
    x0 = 0.0            # skin unrolled): element x in [x0, x0 + period) wraps, for element
    period = 0.2827     # y in [y0, y1]; a press across its two ends presses both
    y0 = 0.0
    y1 = 0.12

A skin description (``[[patch]]`` tables: :mod:`cellbridge.tactile.skin_geometry`) is a
mesh file too: one bridge per element at its atlas position, a cell between each pair of
neighbouring elements (across the seams of patches of one surface and across wrap seams
too), the gateways it names (:mod:`cellbridge.emulator.mesh.skin_mesh`).

A bad file is refused with a :class:`MeshError` whose message names the key and the
problem, so a user can fix it without reading this module.
"""

from __future__ import annotations

import math
import os
import tomllib
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Mapping

from cellbridge.tactile.skin_geometry import Band

from cellbridge.errors import CellbridgeError

DEFAULT_SIDE = 0.040
#: The element model's largest side (cellbridge.tactile.layout.MAX_SIDE): a bridge builds
#: its element from the file's side and could not start beyond it.
MAX_SIDE = 1.0
DEFAULT_BITRATE = 1_000_000
MAX_BRIDGE_ID = 0xFFFE

_TOP_KEYS = {"loss", "ber", "side", "bitrate", "name", "cell", "bridge", "link", "wrap"}
_WRAP_KEYS = {"x0", "period", "y0", "y1"}
_CELL_KEYS = {"id", "loss", "ber"}
_BRIDGE_KEYS = {"id", "cells", "position", "gateway", "tcp"}
_LINK_KEYS = {"a", "b", "loss", "ber"}


class MeshError(CellbridgeError, ValueError):
    """A mesh description that cannot be used; the message names the key and the problem."""


@dataclass(frozen=True)
class Cell:
    id: int
    loss: float | None = None
    ber: float | None = None


@dataclass(frozen=True)
class Bridge:
    id: int
    cells: tuple[int, ...]
    position: tuple[float, float]
    gateway: bool = False
    tcp: int | None = None


@dataclass(frozen=True)
class Link:
    a: int
    b: int
    loss: float | None = None
    ber: float | None = None


@dataclass(frozen=True)
class Mesh:
    """A validated mesh. Build one with :func:`parse_mesh`, :func:`mesh_from_mapping`
    or the generators in :mod:`cellbridge.emulator.mesh.meshgen`."""

    cells: tuple[Cell, ...]
    bridges: tuple[Bridge, ...]
    links: tuple[Link, ...] = ()
    loss: float = 0.0
    ber: float = 0.0
    side: float = DEFAULT_SIDE
    bitrate: int = DEFAULT_BITRATE
    name: str = ""
    #: bands of the skin that close on themselves (a cylinder's skin, unrolled)
    wraps: tuple[Band, ...] = ()
    _by_id: dict[int, Bridge] = field(default_factory=dict, repr=False, compare=False)
    _cell_by_id: dict[int, Cell] = field(default_factory=dict, repr=False, compare=False)
    _link_of: dict[frozenset[int], Link] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Lookups by id: a 10 000-bridge mesh asks these once per pair of neighbours.
        self._by_id.update({b.id: b for b in self.bridges})
        self._cell_by_id.update({c.id: c for c in self.cells})
        for ln in self.links:
            self._link_of.setdefault(frozenset((ln.a, ln.b)), ln)

    def bridge(self, bridge_id: int) -> Bridge:
        try:
            return self._by_id[bridge_id]
        except KeyError:
            raise MeshError(f"bridge {bridge_id}: no such bridge in the mesh") from None

    @property
    def ids(self) -> list[int]:
        return [b.id for b in self.bridges]

    @property
    def gateways(self) -> list[int]:
        return [b.id for b in self.bridges if b.gateway]

    def cell(self, cell_id: int) -> Cell:
        try:
            return self._cell_by_id[cell_id]
        except KeyError:
            raise MeshError(f"cell {cell_id}: no such cell in the mesh") from None

    def members(self, cut: frozenset[int] = frozenset()) -> dict[int, list[int]]:
        """Cell id -> bridges on it (cells in ``cut`` left out)."""
        out: dict[int, list[int]] = {c.id: [] for c in self.cells if c.id not in cut}
        for b in self.bridges:
            for c in b.cells:
                if c in out:
                    out[c].append(b.id)
        return out

    def shared_cells(self, cut: frozenset[int] = frozenset()) -> dict[tuple[int, int], list[int]]:
        """(a, b) with a != b -> the cells both bridges touch (both orders present)."""
        out: dict[tuple[int, int], list[int]] = {}
        for cell, ids in self.members(cut).items():
            for a in ids:
                for b in ids:
                    if a != b:
                        out.setdefault((a, b), []).append(cell)
        return out

    def neighbours(self, cut: frozenset[int] = frozenset(),
                   dead: frozenset[int] = frozenset()) -> dict[int, list[int]]:
        """Bridge -> the bridges that hear it (sorted), ignoring cut cells and dead bridges."""
        out: dict[int, set[int]] = {b.id: set() for b in self.bridges if b.id not in dead}
        for (a, b) in self.shared_cells(cut):
            if a not in dead and b not in dead:
                out[a].add(b)
        return {k: sorted(v) for k, v in out.items()}

    def hops(self, *roots: int, cut: frozenset[int] = frozenset(),
             dead: frozenset[int] = frozenset()) -> dict[int, int]:
        """Bridge -> hops from the nearest of ``roots`` (default: the gateways), over shared
        cells that are not ``cut`` and through bridges that are not ``dead``; bridges no
        path reaches are left out. Keys come in breadth-first order: the roots, then
        outwards (the order a skin boots in, see ``process_up.start_order``)."""
        nb = self.neighbours(cut, dead)
        start = tuple(r for r in (roots or self.gateways) if r not in dead)
        dist = {r: 0 for r in start}
        todo = deque(start)
        while todo:
            b = todo.popleft()
            for n in nb[b]:
                if n not in dist:
                    dist[n] = dist[b] + 1
                    todo.append(n)
        return dist

    def readout_depths(self) -> int:
        """Levels the readout schedule needs (``FirmwareConfig.readout_depths``): the deepest
        bridge's hops from its nearest gateway, and two more for routes that take a detour;
        with more than one gateway, at least the deepest bridge's hops once any one gateway
        has died. The schedule is fixed when the skin starts, and a bridge deeper than its
        last level sends in its parent's slot, always too late: after the failover it is
        listed missing in every frame. (Centre bridge 6 and corner 16 of a 4x4 give 5 levels,
        and bridge 1 is 6 hops from 16 once 6 died: it was unknown for good.)"""
        deepest = max(self.hops().values(), default=0) + 2
        if len(self.gateways) > 1:
            for g in self.gateways:
                deepest = max(deepest, max(self.hops(dead=frozenset((g,))).values(), default=0))
        return deepest

    def reachable(self, cut: frozenset[int] = frozenset(),
                  dead: frozenset[int] = frozenset()) -> set[int]:
        """Bridges with a path of live bridges and uncut cells to a live gateway."""
        return set(self.hops(cut=cut, dead=dead))

    def link_params(self, a: int, b: int, cell: int) -> tuple[float, float]:
        """(loss, ber) of a delivery from a to b over ``cell``: link, then cell, then default."""
        c = self.cell(cell)
        loss = c.loss if c.loss is not None else self.loss
        ber = c.ber if c.ber is not None else self.ber
        ln = self._link_of.get(frozenset((a, b)))
        if ln is not None:
            loss = ln.loss if ln.loss is not None else loss
            ber = ln.ber if ln.ber is not None else ber
        return loss, ber


# ----------------------------------------------------------------------------- parsing


def _where(kind: str, i: int, entry: Mapping[str, Any]) -> str:
    ident = entry.get("id") if isinstance(entry, Mapping) else None
    return f"{kind}[{i}]" + (f" (id {ident})" if isinstance(ident, int) else "")


def _unknown(keys: set[str], allowed: set[str], where: str) -> None:
    extra = sorted(set(keys) - allowed)
    if extra:
        raise MeshError(f"{where}: unknown key '{extra[0]}' (allowed: {', '.join(sorted(allowed))})")


def _int(value: Any, where: str, lo: int, hi: int) -> int:
    if type(value) is not int or not lo <= value <= hi:
        raise MeshError(f"{where}: must be an integer in {lo}..{hi}, got {value!r}")
    return value


def _prob(value: Any, where: str) -> float:
    if type(value) not in (int, float) or not (math.isfinite(value) and 0.0 <= value <= 1.0):
        raise MeshError(f"{where}: must be a probability in 0..1, got {value!r}")
    return float(value)


def _opt_prob(entry: Mapping[str, Any], key: str, where: str) -> float | None:
    return _prob(entry[key], f"{where}.{key}") if key in entry else None


def _table_list(data: Mapping[str, Any], key: str, source: str) -> list[Mapping[str, Any]]:
    raw = data.get(key, [])
    if not isinstance(raw, list) or not all(isinstance(e, Mapping) for e in raw):
        raise MeshError(f"{source}: '{key}' must be an array of tables ([[{key}]])")
    return raw


def mesh_from_mapping(data: Mapping[str, Any], source: str = "mesh") -> Mesh:
    """Validate a parsed mesh (e.g. from TOML) and build a :class:`Mesh`."""
    _unknown(set(data), _TOP_KEYS, source)
    loss = _prob(data.get("loss", 0.0), f"{source}: loss")
    ber = _prob(data.get("ber", 0.0), f"{source}: ber")
    side = data.get("side", DEFAULT_SIDE)
    if type(side) not in (int, float) or not (math.isfinite(side) and 0 < side <= MAX_SIDE):
        raise MeshError(f"{source}: side must be a length > 0 and <= {MAX_SIDE:g} m (an element's "
                        f"side, in metres), got {side!r}")
    bitrate = _int(data.get("bitrate", DEFAULT_BITRATE), f"{source}: bitrate", 1_000, 50_000_000)
    name = data.get("name", "")
    if not isinstance(name, str):
        raise MeshError(f"{source}: name must be a string")

    cells: list[Cell] = []
    cell_ids: set[int] = set()
    for i, e in enumerate(_table_list(data, "cell", source)):
        w = f"{source}: {_where('cell', i, e)}"
        _unknown(set(e), _CELL_KEYS, w)
        if "id" not in e:
            raise MeshError(f"{w}: missing key 'id'")
        cid = _int(e["id"], f"{w}.id", 0, 2**31)
        if cid in cell_ids:
            raise MeshError(f"{w}.id: duplicate cell id {cid}")
        cell_ids.add(cid)
        cells.append(Cell(cid, _opt_prob(e, "loss", w), _opt_prob(e, "ber", w)))

    bridges: list[Bridge] = []
    bridge_ids: set[int] = set()
    tcp_of: dict[int, int] = {}  # a gateway's fixed TCP port -> its bridge
    for i, e in enumerate(_table_list(data, "bridge", source)):
        w = f"{source}: {_where('bridge', i, e)}"
        _unknown(set(e), _BRIDGE_KEYS, w)
        for key in ("id", "cells", "position"):
            if key not in e:
                raise MeshError(f"{w}: missing key '{key}'")
        bid = _int(e["id"], f"{w}.id", 1, MAX_BRIDGE_ID)
        if bid in bridge_ids:
            raise MeshError(f"{w}.id: duplicate bridge id {bid}")
        bridge_ids.add(bid)
        cl = e["cells"]
        if not isinstance(cl, list) or not all(type(c) is int for c in cl):
            raise MeshError(f"{w}.cells: must be an array of cell ids")
        if not cl:
            raise MeshError(f"{w}.cells: bridge {bid} is on no cell")
        for c in cl:
            if c not in cell_ids:
                raise MeshError(f"{w}.cells: cell {c} is not declared in [[cell]]")
        if len(set(cl)) != len(cl):
            raise MeshError(f"{w}.cells: a cell is listed twice")
        pos = e["position"]
        if (not isinstance(pos, list) or len(pos) != 2
                or not all(type(p) in (int, float) and math.isfinite(p) for p in pos)):
            raise MeshError(f"{w}.position: must be [x, y] in metres, got {pos!r}")
        gw = e.get("gateway", False)
        if type(gw) is not bool:
            raise MeshError(f"{w}.gateway: must be true or false, got {gw!r}")
        tcp = e.get("tcp")
        if tcp is not None:
            _int(tcp, f"{w}.tcp", 0, 65535)
            if not gw:
                raise MeshError(f"{w}.tcp: only a gateway serves a TCP port")
            if tcp and tcp in tcp_of:  # 0: any free port, as many as wanted
                raise MeshError(f"{w}.tcp: port {tcp} is already bridge {tcp_of[tcp]}'s (two gateways "
                                f"cannot serve one port)")
            tcp_of[tcp] = bid
        bridges.append(Bridge(bid, tuple(cl), (float(pos[0]), float(pos[1])), gw, tcp))
    if not bridges:
        raise MeshError(f"{source}: no [[bridge]] in the mesh")

    links: list[Link] = []
    link_at: dict[frozenset[int], int] = {}
    cells_of = {b.id: set(b.cells) for b in bridges}
    for i, e in enumerate(_table_list(data, "link", source)):
        w = f"{source}: link[{i}]"
        _unknown(set(e), _LINK_KEYS, w)
        for key in ("a", "b"):
            if key not in e:
                raise MeshError(f"{w}: missing key '{key}'")
            _int(e[key], f"{w}.{key}", 1, MAX_BRIDGE_ID)  # `true` is no bridge id (True == 1)
            if e[key] not in bridge_ids:
                raise MeshError(f"{w}.{key}: missing bridge {e[key]!r} (no [[bridge]] with that id)")
        a, b = e["a"], e["b"]
        if a == b:
            raise MeshError(f"{w}: a link joins two different bridges")
        pair = frozenset((a, b))
        if pair in link_at:
            raise MeshError(f"{w}: link {min(a, b)}-{max(a, b)} is already set by link[{link_at[pair]}] "
                            f"(one [[link]] per pair: which loss would hold?)")
        link_at[pair] = i
        if not cells_of[a] & cells_of[b]:
            raise MeshError(f"{source}: link {a}-{b}: the bridges share no cell")
        links.append(Link(a, b, _opt_prob(e, "loss", w), _opt_prob(e, "ber", w)))

    wraps = []
    for i, e in enumerate(_table_list(data, "wrap", source)):
        w = f"{source}: wrap[{i}]"
        _unknown(set(e), _WRAP_KEYS, w)
        vals = {}
        for key in sorted(_WRAP_KEYS):
            if key not in e:
                raise MeshError(f"{w}: missing key '{key}'")
            v = e[key]
            if type(v) not in (int, float) or not math.isfinite(v):
                raise MeshError(f"{w}.{key}: must be a number (m), got {v!r}")
            vals[key] = float(v)
        if not vals["period"] > 2 * side:
            raise MeshError(f"{w}.period: must be more than two element sides, got {vals['period']!r}")
        if vals["y1"] < vals["y0"]:
            raise MeshError(f"{w}: y1 must be >= y0")
        wraps.append(Band(vals["x0"], vals["period"], vals["y0"], vals["y1"]))
    mesh = Mesh(tuple(cells), tuple(bridges), tuple(links), loss, ber, float(side), bitrate, name, tuple(wraps))
    if not mesh.gateways:
        raise MeshError(f"{source}: no bridge has 'gateway = true'; a mesh needs at least one gateway")
    lost = sorted(bridge_ids - mesh.reachable())
    if lost:
        raise MeshError(f"{source}: bridge {lost[0]} is unreachable: no chain of shared cells leads "
                        f"to a gateway (unreachable: {', '.join(map(str, lost))})")
    _check_positions(mesh, source)
    return mesh


def _check_positions(mesh: Mesh, source: str) -> None:
    """Elements are squares of ``side`` at the positions: they may not overlap. Each
    element is compared with those in its own and the 8 neighbouring side-sized grid
    squares only (linear in the bridges, whatever the layout)."""
    side = mesh.side
    tol = side * (1 - 1e-9)
    grid: dict[tuple[int, int], list[tuple[float, float, int]]] = {}
    for b in mesh.bridges:
        x, y = b.position
        gx, gy = math.floor(x / side), math.floor(y / side)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for x2, y2, other in grid.get((gx + dx, gy + dy), ()):
                    if abs(x2 - x) < tol and abs(y2 - y) < tol:
                        first, second = sorted((other, b.id), key=lambda i: (mesh.bridge(i).position, i))
                        raise MeshError(f"{source}: bridge {second}.position: its element overlaps bridge "
                                        f"{first}'s (elements are {side} m squares)")
        grid.setdefault((gx, gy), []).append((x, y, b.id))


def parse_mesh(text: str, source: str = "mesh") -> Mesh:
    """A mesh from a mesh file's text, or from a skin description's (``[[patch]]`` tables)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise MeshError(f"{source}: not valid TOML: {exc}") from None
    except RecursionError:  # tomllib parses nested arrays and tables recursively
        raise MeshError(f"{source}: not valid TOML: nested too deeply") from None
    if "patch" in data:
        from cellbridge.emulator.mesh.skin_mesh import mesh_from_skin
        from cellbridge.tactile.skin_geometry import SkinError, skin_from_mapping

        try:
            skin = skin_from_mapping(data, source)
        except SkinError as exc:
            raise MeshError(str(exc)) from None
        return mesh_from_skin(skin, source=source)
    return mesh_from_mapping(data, source)


#: Bytes a mesh, skin or scenario file may have: a mesh of every bridge id (65 534) is
#: about 9 MB. A file past it (a gigabyte, /dev/zero) is refused after this much is read,
#: not read whole into memory and parsed for a minute.
MAX_FILE_BYTES = 16 * 2**20


def read_text(path: str, what: str, error: type[ValueError]) -> str:
    """A user's file as text (at most :data:`MAX_FILE_BYTES`); a missing, unreadable or
    larger file is ``error`` naming it."""
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise error(f"{path}: cannot read {what}: {exc.strerror}") from None
    if len(data) > MAX_FILE_BYTES:
        raise error(f"{path}: {what} too large (more than {MAX_FILE_BYTES} bytes)")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise error(f"{path}: {what} is not UTF-8 text") from None


_LOADED: dict[str, tuple[tuple[int, int, int], Mesh]] = {}


def load_mesh(path: str) -> Mesh:
    """Read and validate a mesh file; every problem is a :class:`MeshError` naming the file.

    The last mesh read from each path is kept while the file is unchanged (same inode,
    size and modification time): the bridges ``mesh up`` forks inherit it instead of
    parsing a 10 000-bridge file again each (seconds of CPU apiece).
    """
    try:
        st = os.stat(path)
        key = (st.st_ino, st.st_size, st.st_mtime_ns)
    except OSError:
        key = None
    if key is not None and path in _LOADED and _LOADED[path][0] == key:
        return _LOADED[path][1]
    mesh = parse_mesh(read_text(path, "mesh file", MeshError), path)
    if key is not None:
        _LOADED.clear()  # one file at a time: a process runs one mesh
        _LOADED[path] = (key, mesh)
    return mesh


def _num(v: float) -> str:
    return repr(float(v))


def _toml_string(text: str) -> str:
    """A TOML basic string: quotes, backslashes and control characters escaped."""
    out = []
    for ch in text:
        if ch in '"\\':
            out.append("\\" + ch)
        elif ch < " " and ch != "\t" or ch == "\x7f":
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def mesh_to_toml(mesh: Mesh) -> str:
    """The mesh as a TOML file that :func:`parse_mesh` reads back to an equal mesh."""
    out = []
    if mesh.name:
        out.append(f"name = {_toml_string(mesh.name)}")
    out += [f"loss = {_num(mesh.loss)}", f"ber = {_num(mesh.ber)}", f"side = {_num(mesh.side)}",
            f"bitrate = {mesh.bitrate}", ""]
    for c in mesh.cells:
        out.append("[[cell]]")
        out.append(f"id = {c.id}")
        if c.loss is not None:
            out.append(f"loss = {_num(c.loss)}")
        if c.ber is not None:
            out.append(f"ber = {_num(c.ber)}")
        out.append("")
    for b in mesh.bridges:
        out += ["[[bridge]]", f"id = {b.id}", f"cells = [{', '.join(map(str, b.cells))}]",
                f"position = [{_num(b.position[0])}, {_num(b.position[1])}]"]
        if b.gateway:
            out.append("gateway = true")
        if b.tcp is not None:
            out.append(f"tcp = {b.tcp}")
        out.append("")
    for ln in mesh.links:
        out += ["[[link]]", f"a = {ln.a}", f"b = {ln.b}"]
        if ln.loss is not None:
            out.append(f"loss = {_num(ln.loss)}")
        if ln.ber is not None:
            out.append(f"ber = {_num(ln.ber)}")
        out.append("")
    for w in mesh.wraps:
        out += ["[[wrap]]", f"x0 = {_num(w.x0)}", f"period = {_num(w.period)}", f"y0 = {_num(w.y0)}",
                f"y1 = {_num(w.y1)}", ""]
    return "\n".join(out)

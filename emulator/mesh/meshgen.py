"""Mesh generators: line, ring, grid and random skins.

Bridges are numbered from 1; element positions sit on a square grid of pitch
``side``. In line, ring and grid meshes each pair of neighbouring bridges shares a
cell of its own. A random mesh is a random connected patch of elements where every
2×2 block of element slots is one cell touched by the (2 to 4) bridges in it, so
cells are shared by several bridges and transmissions can collide.
"""

from __future__ import annotations

import random
from collections.abc import Iterable, Sequence

from cellbridge.emulator.mesh.mesh import DEFAULT_SIDE, Bridge, Cell, Mesh, MeshError, mesh_to_toml, parse_mesh


def _finish(cells: dict[int, list[int]], positions: dict[int, tuple[float, float]],
            gateways: Iterable[int], loss: float, ber: float, side: float, name: str) -> Mesh:
    gws = set(gateways)
    unknown = gws - set(positions)
    if unknown:
        raise MeshError(f"gateway {min(unknown)}: no such bridge (bridges are 1..{len(positions)})")
    on: dict[int, list[int]] = {b: [] for b in positions}
    for cid, members in cells.items():
        for b in members:
            on[b].append(cid)
    mesh = Mesh(
        tuple(Cell(c) for c in sorted(cells)),
        tuple(Bridge(b, tuple(on[b]), positions[b], b in gws) for b in sorted(positions)),
        (), loss, ber, side, name=name,
    )
    # Round-trip through the validator: a generator never makes a mesh a file could not hold.
    return parse_mesh(mesh_to_toml(mesh), f"generated {name}")


def line(n: int, gateways: Sequence[int] = (1,), loss: float = 0.0, ber: float = 0.0,
         side: float = DEFAULT_SIDE) -> Mesh:
    """n bridges in a row; cell i joins bridges i and i+1 (n−1 hops end to end)."""
    if n < 1:
        raise MeshError("line: n must be >= 1")
    pos = {i: ((i - 1) * side, 0.0) for i in range(1, n + 1)}
    cells = {i: [i, i + 1] for i in range(1, n)} or {1: [1]}
    return _finish(cells, pos, gateways, loss, ber, side, f"line-{n}")


def ring(n: int, gateways: Sequence[int] = (1,), loss: float = 0.0, ber: float = 0.0,
         side: float = DEFAULT_SIDE) -> Mesh:
    """n bridges whose elements lie on the border of a rectangle; neighbours share a cell."""
    if n < 3:
        raise MeshError("ring: n must be >= 3")
    w = max(2, (n + 3) // 4 + 1)  # border of a w x h rectangle holds 2w + 2h - 4 slots
    h = max(2, (n - 2 * w + 4 + 1) // 2)
    slots = [(x, 0) for x in range(w)] + [(w - 1, y) for y in range(1, h)]
    slots += [(x, h - 1) for x in range(w - 2, -1, -1)] + [(0, y) for y in range(h - 2, 0, -1)]
    if len(slots) < n:
        raise MeshError("ring: internal layout error")
    pos = {i + 1: (slots[i][0] * side, slots[i][1] * side) for i in range(n)}
    cells = {i: [i, i % n + 1] for i in range(1, n + 1)}
    return _finish(cells, pos, gateways, loss, ber, side, f"ring-{n}")


def grid_centre(rows: int, cols: int) -> int:
    """The bridge at the middle of a rows × cols grid (the upper left one of the middle four
    of an even grid): a grid's default gateway."""
    return (rows - 1) // 2 * cols + (cols - 1) // 2 + 1


def grid(rows: int, cols: int, gateways: Sequence[int] | None = None, loss: float = 0.0, ber: float = 0.0,
         side: float = DEFAULT_SIDE) -> Mesh:
    """rows × cols bridges; bridge (r, c) is id r·cols + c + 1; edge neighbours share a cell.

    ``gateways``: default the grid's centre bridge (:func:`grid_centre`), the shallowest
    routing tree one gateway gives: every frame's readout climbs the tree deepest first,
    hop by hop, so its latency grows with the depth (a 4×4's deepest bridge is 4 hops from
    its centre, 6 from a corner), and the centre spreads the skin's records over four cells
    into the gateway, where a corner has two."""
    if rows < 1 or cols < 1:
        raise MeshError("grid: rows and cols must be >= 1")
    if gateways is None:
        gateways = (grid_centre(rows, cols),)
    pos = {r * cols + c + 1: (c * side, r * side) for r in range(rows) for c in range(cols)}
    cells: dict[int, list[int]] = {}
    for r in range(rows):
        for c in range(cols):
            b = r * cols + c + 1
            if c + 1 < cols:
                cells[len(cells) + 1] = [b, b + 1]
            if r + 1 < rows:
                cells[len(cells) + 1] = [b, b + cols]
    return _finish(cells or {1: [1]}, pos, gateways, loss, ber, side, f"grid-{rows}x{cols}")


def random_mesh(n: int, seed: int = 0, gateways: Sequence[int] = (1,), loss: float = 0.0,
                ber: float = 0.0, side: float = DEFAULT_SIDE) -> Mesh:
    """A random connected patch of n elements grown from one slot; 2×2 blocks are cells."""
    if n < 2:
        raise MeshError("random: n must be >= 2")
    rng = random.Random(seed)
    taken = [(0, 0)]
    seen = {(0, 0)}
    frontier = [(1, 0), (-1, 0), (0, 1), (0, -1)]
    while len(taken) < n:
        slot = frontier.pop(rng.randrange(len(frontier)))
        if slot in seen:
            continue
        seen.add(slot)
        taken.append(slot)
        x, y = slot
        frontier += [s for s in ((x + 1, y), (x - 1, y), (x, y + 1), (x, y - 1)) if s not in seen]
    x0 = min(s[0] for s in taken)
    y0 = min(s[1] for s in taken)
    ids = {s: i + 1 for i, s in enumerate(sorted(taken, key=lambda s: (s[1], s[0])))}
    pos = {ids[s]: ((s[0] - x0) * side, (s[1] - y0) * side) for s in taken}
    cells: dict[int, list[int]] = {}
    for bx, by in sorted({(x - dx, y - dy) for x, y in taken for dx in (0, 1) for dy in (0, 1)}):
        members = sorted(ids[s] for s in ((bx, by), (bx + 1, by), (bx, by + 1), (bx + 1, by + 1))
                         if s in ids)
        if len(members) >= 2:
            cells[len(cells) + 1] = members
    return _finish(cells, pos, gateways, loss, ber, side, f"random-{n}-seed{seed}")


def generate(kind: str, size: Sequence[int], **kw: object) -> Mesh:
    """Dispatch for the command line: ``line N``, ``ring N``, ``grid R C``, ``random N``."""
    need = {"line": 1, "ring": 1, "grid": 2, "random": 1}
    if kind not in need:
        raise MeshError(f"unknown mesh kind {kind!r} (line, ring, grid, random)")
    if len(size) != need[kind]:
        raise MeshError(f"{kind} takes {need[kind]} size number(s), got {len(size)}")
    fn = {"line": line, "ring": ring, "grid": grid, "random": random_mesh}[kind]
    if kind != "random":
        kw.pop("seed", None)
    return fn(*size, **kw)  # type: ignore[operator]  # each generator takes its kind's size numbers, counted above

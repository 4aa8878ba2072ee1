"""The emulated skin of a skin description: a mesh with one bridge per element.

Each element of the description (:mod:`cellbridge.tactile.skin_geometry`) is a bridge at
its atlas position (what its HELLO announces); each pair of neighbouring elements shares
a cell of its own, as in a grid mesh, wherever the two lie: inside a patch, across the
seam of two patches of one surface, across a wrap seam. The description's gateways are
the gateway bridges; its bands become the mesh's wraps, so the world presses both ends
of a band under a press across its seam.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from cellbridge.emulator.mesh.mesh import Mesh, MeshError, mesh_from_mapping
from cellbridge.tactile.layout import SkinLayout
from cellbridge.tactile.skin_geometry import SkinGeometry

__all__ = ["mesh_from_skin", "neighbour_pairs"]


def neighbour_pairs(skin: SkinGeometry) -> np.ndarray:
    """(E, 2) rows (into the skin's per-element arrays) of edge neighbours, across wrap
    seams too; each pair once, i < j."""
    lay = skin.layout()
    pairs = [lay.edges]
    for b in skin.bands:
        rows = np.flatnonzero(b.holds(lay.centres[:, 0], lay.centres[:, 1]))
        moved = lay.centres[rows].copy()
        far = moved[:, 0] >= b.x0 + 0.5 * b.period
        moved[far, 0] -= b.period
        twin = SkinLayout(moved, side=lay.side, ids=lay.ids[rows], neighbour_gap=lay.neighbour_gap)
        pairs.append(rows[twin.edges])
    e = np.sort(np.concatenate(pairs), axis=1)
    return np.unique(e, axis=0)


def _gatewayless(skin: SkinGeometry, pairs: list[list[int]], gateway_rows: set[int]) -> list[int] | None:
    """Rows of the first group of elements joined by cells (``pairs``) holding no gateway
    (in row order), or None: every element reaches one."""
    root = list(range(skin.n))

    def find(i: int) -> int:
        while root[i] != i:
            root[i] = root[root[i]]
            i = root[i]
        return i

    for i, j in pairs:
        root[find(i)] = find(j)
    served = {find(r) for r in gateway_rows}
    for r in range(skin.n):
        if find(r) not in served:
            return [k for k in range(skin.n) if find(k) == find(r)]
    return None


def mesh_from_skin(skin: SkinGeometry, loss: float = 0.0, ber: float = 0.0, source: str | None = None) -> Mesh:
    """The mesh of ``skin`` (validated as a mesh file is: every bridge must reach a gateway).
    ``source``: the file it came from, named by every error (default: the skin's name).

    Elements that reach no gateway are refused naming their patches and link: cells join
    neighbouring elements of one surface only, so a surface needs a gateway of its own."""
    where = source or skin.name or "skin"
    ids = skin.ids.tolist()
    gateways = {bid: g for bid, g in zip(skin.gateway_ids(), skin.gateways)}
    pairs = neighbour_pairs(skin).tolist()
    alone = _gatewayless(skin, pairs, {skin.row_of(b) for b in gateways})
    if alone is not None:
        names = list(dict.fromkeys(skin.patches[int(skin.patch_of[r])].name for r in alone))
        link = skin.patch(names[0]).link
        raise MeshError(f"{where}: patch{'es' if len(names) > 1 else ''} {', '.join(repr(n) for n in names)} of link "
                        f"{link!r} reach no gateway ({len(alone)} elements): cells join neighbouring elements of "
                        f"one surface only, so each surface needs a [[gateway]] of its own")
    cells_of: dict[int, list[int]] = {b: [] for b in ids}
    cells = []
    for k, (i, j) in enumerate(pairs, start=1):
        cells.append({"id": k})
        cells_of[ids[i]].append(k)
        cells_of[ids[j]].append(k)
    if not cells:  # a skin of one element
        cells.append({"id": 1})
        cells_of[ids[0]].append(1)
    bridges: list[dict[str, Any]] = []
    for r, b in enumerate(ids):
        entry: dict[str, Any] = {"id": b, "cells": cells_of[b],
                                 "position": [float(skin.atlas[r, 0]), float(skin.atlas[r, 1])]}
        if b in gateways:
            entry["gateway"] = True
            if gateways[b].tcp is not None:
                entry["tcp"] = gateways[b].tcp
        if not entry["cells"]:
            g = gateways.get(b)
            raise MeshError(f"{where}: element {b} has no neighbour"
                            + ("" if g else ": no cell joins it to the rest, and it is no gateway"))
        bridges.append(entry)
    data = {"name": skin.name, "side": skin.side, "loss": loss, "ber": ber, "cell": cells, "bridge": bridges,
            "wrap": [{"x0": b.x0, "period": b.period, "y0": b.y0, "y1": b.y1} for b in skin.bands]}
    try:
        return mesh_from_mapping(data, where)
    except MeshError as exc:
        raise MeshError(f"{exc} (in a skin, each link's surfaces need a gateway of their own: cells join "
                        f"neighbouring elements of one surface only)") from None

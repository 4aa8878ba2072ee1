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


def mesh_from_skin(skin: SkinGeometry, loss: float = 0.0, ber: float = 0.0) -> Mesh:
    """The mesh of ``skin`` (validated as a mesh file is: every bridge must reach a gateway)."""
    ids = skin.ids.tolist()
    gateways = {bid: g for bid, g in zip(skin.gateway_ids(), skin.gateways)}
    cells_of: dict[int, list[int]] = {b: [] for b in ids}
    cells = []
    for k, (i, j) in enumerate(neighbour_pairs(skin).tolist(), start=1):
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
            raise MeshError(f"{skin.name or 'skin'}: element {b} has no neighbour"
                            + ("" if g else ": no cell joins it to the rest, and it is no gateway"))
        bridges.append(entry)
    data = {"name": skin.name, "side": skin.side, "loss": loss, "ber": ber, "cell": cells, "bridge": bridges,
            "wrap": [{"x0": b.x0, "period": b.period, "y0": b.y0, "y1": b.y1} for b in skin.bands]}
    try:
        return mesh_from_mapping(data, skin.name or "skin")
    except MeshError as exc:
        raise MeshError(f"{exc} (in a skin, each link's surfaces need a gateway of their own: cells join "
                        f"neighbouring elements of one surface only)") from None

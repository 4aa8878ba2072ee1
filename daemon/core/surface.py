"""Contacts and topology on the robot: what the skin description adds to the messages.

The estimator works on the atlas (the skin's surfaces unrolled side by side); a
subscriber wants the contact on the robot. :func:`contact_fields` adds each contact's
link, patch, 3-D position, normal and force vector in the link frame (and the position's
covariance carried there), :func:`skin_report` the links, patches and element frames for
``topology``. Without a skin description the layout's own plane is the frame: ``link``
None, the position (x, y, 0), the normal +z.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from cellbridge.tactile.skin_geometry import SkinGeometry
from numpy.typing import NDArray

__all__ = ["contact_fields", "skin_report"]


def contact_fields(skin: SkinGeometry | None, contacts: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each contact (a ``contact`` message's dict, with ``x``, ``y``, ``force`` and ``cov``)
    with ``link``, ``patch``, ``position``, ``normal``, ``force_vector`` and
    ``position_cov`` added. The skin measures a normal load: the force vector is
    ``-force·normal`` (the push into the surface), None when the force is not known."""
    if not contacts:
        return contacts
    xs = [float(c["x"]) for c in contacts]
    ys = [float(c["y"]) for c in contacts]
    points = skin.locate(xs, ys, [_chart_of(skin, c) for c in contacts]) if skin is not None else None
    Vec = tuple[float, float, float]
    placed: list[tuple[str | None, str | None, Vec, Vec, Vec, Vec]] = []
    for k in range(len(contacts)):
        if points is None:
            placed.append((None, None, (xs[k], ys[k], 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)))
        else:
            sp = points[k]
            placed.append((sp.link, sp.patch, sp.position, sp.normal, sp.tangent_x, sp.tangent_y))
    # every contact's Jacobian (3, 2): atlas (x, y) -> link frame, carried in one pass
    jac = np.array([(tx, ty) for *_, tx, ty in placed], dtype=np.float64).transpose(0, 2, 1)
    covs = _carried(jac, np.array([c["cov"] for c in contacts], dtype=np.float64)).tolist()
    out = []
    for c, (link, patch, pos, nrm, _, _), cov in zip(contacts, placed, covs):
        f = float(c["force"])
        fv = [-f * n for n in nrm] if math.isfinite(f) else None
        out.append({**c, "link": link, "patch": patch, "position": list(pos), "normal": list(nrm),
                    "force_vector": fv, "position_cov": cov})
    return out


def _chart_of(skin: SkinGeometry, contact: dict[str, Any]) -> int:
    """The chart of a contact's elements (-1: none of them is the skin's): where it is,
    whatever chart its fitted centre lies nearest (a centre past a patch's edge can lie
    nearer the next chart of the atlas, another link's)."""
    for e in contact.get("elements") or ():
        try:
            return int(skin.chart_of[skin.row_of(e)])
        except (KeyError, TypeError, ValueError):
            continue
    return -1


def _carried(jac: NDArray[np.float64], cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """``jac @ cov @ jac.T`` of each contact (``jac`` (k, 3, 2), ``cov`` (k, 2, 2)), where a
    zero entry of ``jac`` contributes nothing, also against an infinite variance: an atlas
    axis the readings leave open (σ infinite) leaves open the link coordinates it moves,
    and no other (0 · inf taken literally made the whole covariance NaN, the surface
    normal's coordinate included, which the patch pins)."""
    terms = jac[:, :, None, :, None] * jac[:, None, :, None, :]  # (k, 3, 3, 2, 2): J[i, a] J[j, b]
    with np.errstate(invalid="ignore"):
        out = np.where(terms != 0, terms * cov[:, None, None, :, :], 0.0)
    return np.asarray(out.sum(axis=(3, 4)), dtype=np.float64)


def skin_report(skin: SkinGeometry | None) -> dict[str, Any] | None:
    """The skin description for ``topology``: links (parent, pose in the parent's frame
    at the joints' zero), patches, gateways, and each element's link, patch, grid place,
    centre and normal in its link's frame; None without a description."""
    if skin is None:
        return None
    return {
        "name": skin.name,
        "side": skin.side,
        "urdf": skin.urdf,
        "links": [{"name": ln.name, "parent": ln.parent, "origin": [list(r) for r in ln.origin],
                   "declared": ln.declared} for ln in skin.links],
        "patches": [{"name": p.name, "link": p.link, "shape": p.shape, "rows": p.rows, "cols": p.cols,
                     "pitch": p.pitch, "col_pitch": p.col_pitch, "radius": p.radius if p.shape == "cylinder" else None,
                     "wrap": p.wrap, "pose": [list(r) for r in p.pose], "start": list(p.start),
                     "first_id": p.first_id} for p in skin.patches],
        "gateways": [{"name": g.name, "bridge": b} for g, b in zip(skin.gateways, skin.gateway_ids())],
        "elements": {
            "ids": skin.ids.tolist(),
            "patch": [skin.patches[int(i)].name for i in skin.patch_of],
            "row": skin.row.tolist(),
            "col": skin.col.tolist(),
            "position": skin.position.tolist(),
            "normal": skin.normal.tolist(),
        },
    }

"""The daemon's messages of a skin on a robot (the arm of ``cellbridge robot run``), for the
views' tests: ``topology`` with its ``skin`` (links, patches, element frames) and
``contact`` with link, patch, 3-D position, normal and force vector, made by the
daemon's own functions (:func:`cellbridge.daemon.core.surface.skin_report`,
:func:`~cellbridge.daemon.core.surface.contact_fields`) from the arm's skin description.
"""

from __future__ import annotations

from typing import Any

from cellbridge.daemon.core.surface import contact_fields, skin_report
from cellbridge.emulator.world.robot_world import arm_skin
from cellbridge.tactile.skin_geometry import SkinGeometry

SOURCE = "robot:5560"
# (patch, row, col, force N, diameter m, offset along the atlas's x m) of the presses shown
PRESSES = (("forearm", 1, 3, 3.0, 0.016, 0.008), ("chest_right", 1, 0, 1.5, 0.012, -0.005))


def skin() -> SkinGeometry:
    return arm_skin()


def layout(sk: SkinGeometry) -> dict[str, Any]:
    return {"side": sk.side, "ids": sk.ids.tolist(), "x": sk.atlas[:, 0].tolist(), "y": sk.atlas[:, 1].tolist()}


def topology(sk: SkinGeometry, seq: int = 0) -> dict[str, Any]:
    return {"v": 2, "seq": seq, "source": SOURCE, "bridges": {}, "gateways": {}, "layout": layout(sk),
            "skin": skin_report(sk)}


def pressed(sk: SkinGeometry) -> dict[int, float]:
    """Bridge -> force of the elements under :data:`PRESSES`."""
    return {sk.element_id(p, r, c): f for p, r, c, f, _, _ in PRESSES}


def element(sk: SkinGeometry, seq: int = 0) -> dict[str, Any]:
    forces = {int(b): 0.0 for b in sk.ids.tolist()}
    forces.update(pressed(sk))
    ids = sorted(forces)
    return {"v": 2, "seq": seq, "source": SOURCE, "bridge": ids, "force": [forces[b] for b in ids],
            "area": [1e-4] * len(ids), "dc1": [0.0] * len(ids), "dc2": [0.0] * len(ids),
            "valid": [True] * len(ids), "touched": [forces[b] > 0 for b in ids], "status": [0] * len(ids),
            "t_sample": [float(seq)] * len(ids)}


def contacts(sk: SkinGeometry) -> list[dict[str, Any]]:
    out = []
    for k, (p, r, c, f, d, dx) in enumerate(PRESSES):
        x, y = sk.atlas[sk.row_of(sk.element_id(p, r, c))]
        out.append({"id": 7 + k, "x": float(x) + dx, "y": float(y), "force": f, "diameter": d,
                    "observable": [True, True], "valid": True, "missed": 0, "sigma_x": 1e-3, "sigma_y": 1e-3,
                    "elements": [sk.element_id(p, r, c)], "cov": [[1e-6, 0.0], [0.0, 1e-6]]})
    return contact_fields(sk, out)


def contact(sk: SkinGeometry, seq: int = 0) -> dict[str, Any]:
    return {"v": 2, "seq": seq, "source": SOURCE, "t_sample": float(seq), "contacts": contacts(sk)}


def reply(sk: SkinGeometry) -> Any:
    """A control socket's answers: ``topology`` with the skin."""
    def answer(request: Any) -> Any:
        rid = request.get("id") if isinstance(request, dict) else None
        if isinstance(request, dict) and request.get("cmd") == "topology":
            return dict(topology(sk), id=rid, ok=True)
        return {"v": 1, "id": rid, "ok": True}
    return answer

"""A contact's position covariance carried into its link's frame (``position_cov``).

An axis the readings leave open has an infinite variance (its σ covers every position);
the link frame's coordinate that the axis does not move (the normal's, on a flat patch)
must stay exactly known, not become NaN: 0 · inf taken literally made the whole row and
column NaN, and a subscriber got no number it could use for any axis."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from cellbridge.daemon.core.surface import contact_fields
from cellbridge.daemon.shell.skin_file import load_skin

HUMANOID = Path(__file__).resolve().parents[1] / "cellbridge" / "skins" / "humanoid.toml"


@pytest.fixture(scope="module")
def skin():
    return load_skin(HUMANOID)


def _centres(skin, n: int) -> list[tuple[float, float]]:
    """Atlas points spread over the skin's elements (cylinders and planes alike)."""
    c = skin.layout().centres
    return [(float(c[i, 0]), float(c[i, 1])) for i in np.linspace(0, len(c) - 1, n).astype(int)]


def _contact(cov: list[list[float]], x: float = 0.02, y: float = 0.02) -> dict:
    return {"id": 1, "x": x, "y": y, "force": 2.0, "cov": cov}


def test_an_open_axis_on_a_flat_skin_stays_open_and_the_normal_stays_known() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        (c,) = contact_fields(None, [_contact([[3.4e-05, 0.0], [0.0, math.inf]])])
    cov = np.array(c["position_cov"])
    assert not np.isnan(cov).any(), cov
    assert cov[0, 0] == 3.4e-05 and cov[1, 1] == math.inf
    assert (cov[2] == 0).all() and (cov[:, 2] == 0).all()  # along the normal: on the surface
    assert cov[0, 1] == cov[1, 0] == 0


def test_a_finite_covariance_is_the_jacobian_product_on_every_patch(skin) -> None:
    rng = np.random.default_rng(3)
    for x, y in _centres(skin, 25):
        a = rng.normal(size=(2, 2))
        c2 = a @ a.T * 1e-6
        (c,) = contact_fields(skin, [_contact(c2.tolist(), x, y)])
        sp = skin.locate([x], [y])[0]
        jac = np.array([sp.tangent_x, sp.tangent_y]).T
        assert np.allclose(np.array(c["position_cov"]), jac @ c2 @ jac.T, rtol=1e-12, atol=1e-18)


def test_an_open_axis_on_any_patch_is_open_where_it_moves_and_nan_nowhere(skin) -> None:
    for x, y in _centres(skin, 25):
        (c,) = contact_fields(skin, [_contact([[1e-6, 0.0], [0.0, math.inf]], x, y)])
        cov = np.array(c["position_cov"])
        sp = skin.locate([x], [y])[0]
        ty = np.array(sp.tangent_y)
        assert not np.isnan(cov).any(), cov
        moved = np.abs(ty) > 0  # the link coordinates the open axis moves have no bound
        assert np.isinf(np.diag(cov)[moved]).all()
        assert np.isfinite(np.diag(cov)[~moved]).all()


def test_a_frames_contacts_are_each_carried_as_if_alone(skin) -> None:
    """A frame's contacts are placed and carried together: each one's fields are what it
    gets alone (an open axis of one never reaches another's covariance)."""
    rng = np.random.default_rng(4)
    contacts = []
    for k, (x, y) in enumerate(_centres(skin, 12)):
        a = rng.normal(size=(2, 2))
        cov = (a @ a.T * 1e-6).tolist()
        if k % 3 == 0:
            cov = [[cov[0][0], 0.0], [0.0, math.inf]]
        contacts.append({**_contact(cov, x, y), "id": k, "force": 1.0 + k})
    together = contact_fields(skin, contacts)
    assert len({c["patch"] for c in together}) > 1
    for c, alone in zip(together, (contact_fields(skin, [c])[0] for c in contacts)):
        assert repr(c) == repr(alone)


_TWO_LINKS = """side = 0.04
[[link]]
name = "palm"
[[link]]
name = "thumb"
[[patch]]
name = "palm"
link = "palm"
shape = "plane"
rows = 3
cols = 3
[[patch]]
name = "thumb"
link = "thumb"
shape = "plane"
rows = 3
cols = 3
[[gateway]]
name = "g"
patch = "palm"
[[gateway]]
name = "h"
patch = "thumb"
"""


def test_a_contact_fitted_past_its_patch_s_edge_stays_on_its_elements_link() -> None:
    """A press at a patch's edge with its centre off the skin touches only the edge
    column, and its fitted centre can lie past the edge, into the margin between two
    charts of the atlas. It is on its elements' link (the palm), on the palm's plane
    extended; the nearest chart (the thumb's, past half the margin) put it on another
    link, at a precise wrong place."""
    from cellbridge.tactile.skin_geometry import ATLAS_MARGIN, parse_skin

    skin = parse_skin(_TWO_LINKS, "hand.toml")
    palm, thumb = skin.charts
    assert thumb.x0 - (palm.x0 + palm.width) == pytest.approx(ATLAS_MARGIN * skin.side)
    edge = skin.element_id("palm", 1, 2)  # the palm's last column, middle row
    ex, ey = skin.atlas[skin.row_of(edge)]
    x = palm.x0 + palm.width + 0.6 * ATLAS_MARGIN * skin.side  # past the middle of the margin
    (c,) = contact_fields(skin, [{**_contact([[1e-6, 0.0], [0.0, 1e-6]], x, float(ey)), "elements": [edge]}])
    assert c["link"] == "palm" and c["patch"] == "palm"
    assert c["position"] == pytest.approx([x - palm.x0 + palm.u0, float(ey) - palm.y0 + palm.v0, 0.0])

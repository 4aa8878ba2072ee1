"""A skin description end to end: its emulated skin (virtual time) read by the daemon's core.

A press across a cylinder's wrap seam, and one across the seam of two patches of one link,
are each one contact with one id, published at the right point of the link frame with the
normal and force vector there."""

from __future__ import annotations

import math

import numpy as np
import pytest
from cellbridge.emulator.mesh.skin_mesh import mesh_from_skin
from cellbridge.emulator.world.world import Contact, World
from cellbridge.tactile.skin_geometry import parse_skin

from cellbridge.skin_run import run_daemon_on_skin
from support.skin_descriptions import SKIN


@pytest.fixture(scope="module")
def skin():
    return parse_skin(SKIN, "test.toml")


def _contacts(skin, press: Contact, seconds: float = 4.0) -> tuple[list[dict], dict]:
    world = World(mesh_from_skin(skin), [press])
    reports, topology = [], {}
    for _t, topic, m in run_daemon_on_skin(skin, world, seconds):
        if topic == "contact":
            reports += [c for c in m["contacts"] if c["missed"] == 0]
        elif topic == "topology":
            topology = m
    return reports, topology


def test_a_press_across_the_wrap_seam_is_one_contact_at_its_point_on_the_forearm(skin) -> None:
    (band,) = skin.bands
    x = band.x0 + band.period - 0.004  # 4 mm before the cut, 6 mm of the disk across it
    reports, topology = _contacts(skin, Contact(2.5, 1.2, x, 0.045, 3.0, 0.02))
    assert len(reports) > 20 and {c["id"] for c in reports} == {reports[0]["id"]}
    c = reports[len(reports) // 2]
    first, last = skin.element_id("fore", 1, 0), skin.element_id("fore", 1, 6)
    assert {first, last} <= set(c["elements"])
    angle = (x - band.x0 - 0.5 * skin.patches[0].col_pitch) / 0.045  # from column 0's centre
    # the patch starts at z = 0.05 (row 0's centre, atlas y = 0.02): atlas y 0.045 is z = 0.075,
    # 5 mm into row 1 (so both axes are resolved)
    want = np.array([0.045 * math.cos(angle), 0.045 * math.sin(angle), 0.075])
    assert c["link"] == "forearm" and c["patch"] == "fore"
    assert c["observable"] == [True, True]
    assert np.linalg.norm(np.array(c["position"]) - want) < 1e-3
    normal = np.array([math.cos(angle), math.sin(angle), 0.0])
    assert np.allclose(c["normal"], normal, atol=0.03)
    assert np.allclose(c["force_vector"], -c["force"] * np.array(c["normal"]))
    assert c["force"] == pytest.approx(3.0, rel=0.03)
    sk = topology["skin"]
    assert [p["name"] for p in sk["patches"]] == ["fore", "chest_l", "chest_r"]
    assert {ln["name"] for ln in sk["links"]} == {"torso", "forearm"}


def test_a_press_across_two_patches_of_the_torso_is_one_contact(skin) -> None:
    i = skin.row_of(skin.element_id("chest_r", 0, 0))
    x, y = skin.atlas[i, 0] - 0.022, skin.atlas[i, 1] + 0.016  # across both seams: 4 elements, 2 patches
    reports, _ = _contacts(skin, Contact(2.5, 1.2, x, y, 2.5, 0.016))
    assert len(reports) > 20 and {c["id"] for c in reports} == {reports[0]["id"]}
    c = reports[len(reports) // 2]
    assert {skin.element_id("chest_l", 0, 1), skin.element_id("chest_r", 0, 0)} <= set(c["elements"])
    assert c["link"] == "torso" and c["patch"] == "chest_l"
    assert c["observable"] == [True, True]
    assert np.linalg.norm(np.array(c["position"]) - [0.08 - 0.022, 0.016, 0.1]) < 1e-3
    assert c["normal"] == pytest.approx([0.0, 0.0, 1.0])
    assert c["force"] == pytest.approx(2.5, rel=0.03)

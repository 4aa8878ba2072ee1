"""Skin descriptions: patches on link surfaces, their elements in link frames, the atlas,
and contacts across a wrap seam and across the seam of two patches of one link."""

from __future__ import annotations

import math

import numpy as np
import pytest
from cellbridge.tactile import ContactEstimator, ContactTracker, skin_response
from cellbridge.tactile.seam_estimator import SeamEstimator
from cellbridge.tactile.skin_geometry import SkinError, parse_skin, pose_matrix

from support.skin_descriptions import SKIN


@pytest.fixture(scope="module")
def skin():
    return parse_skin(SKIN, "test.toml")


def test_cylinder_elements_sit_on_the_surface_with_outward_normals(skin) -> None:
    fore = skin.patch_of == 0
    p, n = skin.position[fore], skin.normal[fore]
    assert np.allclose(np.hypot(p[:, 0], p[:, 1]), 0.045)  # on the cylinder about the patch's z
    assert np.allclose(n[:, :2] * 0.045, p[:, :2]) and np.allclose(n[:, 2], 0.0)
    # element (row 1, col 0): angle 0 (the patch frame's x), 1 pitch along the axis
    i = skin.row_of(skin.element_id("fore", 1, 0))
    assert np.allclose(p[i], [0.045, 0.0, 0.05 + 0.04])
    # the grid closes: 7 columns of 2π·r/7, the seam one pitch wide like every other
    assert skin.patches[0].col_pitch == pytest.approx(2 * math.pi * 0.045 / 7)
    (band,) = skin.bands
    assert band.period == pytest.approx(2 * math.pi * 0.045)


def test_plane_elements_and_link_poses(skin) -> None:
    i = skin.row_of(skin.element_id("chest_r", 1, 1))
    assert np.allclose(skin.position[i], [0.08 + 0.04, 0.04, 0.1]) and np.allclose(skin.normal[i], [0, 0, 1])
    assert np.allclose(skin.link_pose("forearm"), pose_matrix((0.3, 0, 0), (0, math.pi / 2, 0)))


def test_patches_on_one_surface_share_a_chart_and_the_seam_between_them_is_a_neighbour_seam(skin) -> None:
    assert len(skin.charts) == 2 and skin.charts[1].patches == ("chest_l", "chest_r")
    lay = skin.layout()
    a, b = lay.index_of([skin.element_id("chest_l", 0, 1), skin.element_id("chest_r", 0, 0)])
    assert b in lay.neighbours(int(a))


def _press(skin, est, x, y, force=3.0, diameter=0.02):
    disks = [(x, y, force, diameter)]
    for band in skin.bands:
        disks += band.ghosts(disks, skin.side)
    d1, d2 = skin_response(skin.layout(), disks)
    return est.estimate(d1, d2)


def test_a_press_across_the_wrap_seam_is_one_contact_at_the_right_3d_point(skin) -> None:
    (band,) = skin.bands
    lay = skin.layout()
    plain = ContactEstimator(lay)
    seam = SeamEstimator(lay, bands=skin.bands)
    for x in (band.x0 + 0.003, band.x0 + band.period - 0.004):  # either side of the cut
        assert len(_press(skin, plain, x, 0.06)) == 2  # the flat atlas alone: two halves
        (c,) = _press(skin, seam, x, 0.06)
        assert c.x == pytest.approx(x, abs=1e-4) and c.y == pytest.approx(0.06, abs=1e-4)
        assert c.force == pytest.approx(3.0, rel=0.01)
        first, last = skin.element_id("fore", 1, 0), skin.element_id("fore", 1, 6)
        assert set(c.elements) == {first, last}
        (sp,) = skin.locate([c.x], [c.y])
        angle = (x - band.x0 - 0.5 * skin.patches[0].col_pitch) / 0.045  # from element column 0
        want = [0.045 * math.cos(angle), 0.045 * math.sin(angle), 0.05 + 0.04]
        assert sp.link == "forearm" and sp.patch == "fore"
        assert np.allclose(sp.position, want, atol=2e-4)
        assert np.allclose(sp.normal, [math.cos(angle), math.sin(angle), 0.0], atol=5e-3)


def test_a_press_across_two_patches_of_one_link_is_one_contact(skin) -> None:
    est = SeamEstimator(skin.layout(), bands=skin.bands)
    i = skin.row_of(skin.element_id("chest_r", 0, 0))
    x = skin.atlas[i, 0] - 0.021  # 1 mm into chest_l from the seam of the two patches
    (c,) = _press(skin, est, x, skin.atlas[i, 1] + 0.02, 2.0, 0.015)
    assert set(c.elements) == {skin.element_id("chest_l", 0, 1), skin.element_id("chest_l", 1, 1),
                               skin.element_id("chest_r", 0, 0), skin.element_id("chest_r", 1, 0)}
    (sp,) = skin.locate([c.x], [c.y])
    assert sp.link == "torso" and sp.patch == "chest_l"
    assert np.allclose(sp.position, [0.08 - 0.021, 0.02, 0.1], atol=2e-4)


def test_a_press_sliding_across_the_wrap_seam_keeps_its_id(skin) -> None:
    (band,) = skin.bands
    lay = skin.layout()
    tracker = ContactTracker(SeamEstimator(lay, bands=skin.bands), birth_frames=2)
    ids = set()
    seen = 0
    for k, x in enumerate(np.linspace(band.x0 + band.period - 0.03, band.x0 + band.period + 0.03, 41)):
        disks = [(band.wrap(float(x)), 0.06, 3.0, 0.02)]
        disks += band.ghosts(disks, skin.side)
        d1, d2 = skin_response(lay, disks)
        out = tracker.update(d1, d2, t=k * 0.01)
        assert len(out) <= 1
        ids |= {tc.id for tc in out}
        if out and out[0].contact.observable[0]:  # (inside one column: its centre, not resolved)
            seen += 1
            assert abs(((out[0].contact.x - float(x)) + band.period / 2) % band.period - band.period / 2) < 5e-4
    assert ids == {0} and seen >= 10


def test_two_half_shells_on_one_cylinder_close_it_together() -> None:
    text = """
side = 0.04
[[link]]
name = "arm"
[[patch]]
name = "front"
link = "arm"
shape = "cylinder"
radius = 0.05
rows = 2
cols = 4
col_pitch = 0.039269908169872414
[[patch]]
name = "back"
link = "arm"
shape = "cylinder"
radius = 0.05
rows = 2
cols = 4
col_pitch = 0.039269908169872414
rpy = [0.0, 0.0, 3.141592653589793]
[[gateway]]
name = "g"
patch = "front"
"""
    with pytest.raises(SkinError, match="less than the element side"):
        parse_skin(text)
    s = parse_skin(text.replace("0.039269908169872414", "0.0401").replace("radius = 0.05", "radius = 0.0511"))
    assert len(s.charts) == 1 and s.charts[0].patches == ("front", "back")
    assert len(s.bands) == 1 and s.bands[0].period == pytest.approx(2 * math.pi * 0.0511)


@pytest.mark.parametrize("change, message", [
    (('link = "forearm"', 'link = "elbow"'), "no link 'elbow'"),
    (("cols = 7", "cols = 3"), "at least 4 columns"),
    (("radius = 0.045", "radius = 0.02"), "pitch around"),
    (('origin = [0.08, 0.0, 0.1]', 'origin = [0.06, 0.0, 0.1]'), "overlap"),
    (('[[gateway]]\nname = "chest"\npatch = "chest_l"', '[[gateway]]\nname = "chest"\npatch = "belly"'),
     "no patch 'belly'"),
    (("shape = \"plane\"\nrows = 2\ncols = 2\norigin = [0.0", "shape = \"plane\"\nwrap = true\nrows = 2\ncols = 2\norigin = [0.0"),
     "only a cylinder"),
    (("rows = 3", "rows = 3\ncolour = 1"), "unknown key 'colour'"),
    # a link's name is its contacts' frame id in ROS 2 and Foxglove: a NUL ends it in C++,
    # and a name cut to fit a view would read as another link's
    (('link = "forearm"', 'link = "fore\\u0000arm"'), "none a control character"),
    (('link = "forearm"', 'link = "fore\\u001b[2Jarm"'), "none a control character"),
    (('link = "forearm"', 'link = "' + "f" * 65 + '"'), "1 to 64 characters"),
    # two gateways on one TCP port: `mesh up --tcp` cannot serve both (0: any free port)
    (('patch = "fore"\n[[gateway]]\nname = "chest"\npatch = "chest_l"',
      'patch = "fore"\ntcp = 7100\n[[gateway]]\nname = "chest"\npatch = "chest_l"\ntcp = 7100'),
     "gateway\\[1\\].tcp: port 7100 is already gateway 'arm'"),
    # every view and ROS 2 take a place beyond 1 km of its frame's origin as unknown: a
    # description putting its elements or links there is refused, not published as unknown
    (("origin = [0.0, 0.0, 0.05]", "origin = [1e300, 0.0, 0.05]"), "patch\\[0\\] \\(fore\\).origin: must lie within"),
    (("origin = [0.3, 0.0, 0.0]", "origin = [1e308, 0.0, 0.0]"), "link\\[1\\].origin: must lie within"),
    (("origin = [0.08, 0.0, 0.1]", "origin = [0.08, 0.0, 0.1]\nstart = [999.9, 0.0]"),
     "patch\\[2\\] \\(chest_r\\): element \\(0, 1\\) lies at \\(1000.02, .* in link 'torso'"),
    (("radius = 0.045", "radius = 1e300"), "patch\\[0\\] \\(fore\\).radius: must be <= 1000"),
    # a wrap whose columns leave a seam wider than neighbour_gap: no band (it did not wrap),
    # its columns no neighbours (each a contact of its own, no cell between them)
    (("radius = 0.045", "radius = 0.06"), "patch\\[0\\] \\(fore\\): its columns are 0.05385.* m apart"),
    (("cols = 2\norigin = [0.0, 0.0, 0.1]", "cols = 2\npitch = 0.06\ncol_pitch = 0.04\norigin = [0.0, 0.0, 0.1]"),
     "patch\\[1\\] \\(chest_l\\): its rows are 0.06 m apart"),
    # the skin's name is in every message about it and in topology: a name as the others'
    (('name = "test"', 'name = "te\\u001b[2Jst"'), "name: must be a name of 1 to 64"),
])
def test_bad_descriptions_are_refused_naming_the_key(change, message) -> None:
    text = SKIN.replace(*change)
    assert text != SKIN
    with pytest.raises(SkinError, match=message):
        parse_skin(text, "test.toml")


def test_a_point_is_on_the_patch_of_the_nearest_element_of_its_own_chart(skin) -> None:
    """locate's patch: the nearest element of the point's own chart (the shorter way round a
    band; of equally near ones, the first row), whatever lies nearer on another chart,
    searched over every element of the skin here."""
    rng = np.random.default_rng(11)
    lo, hi = skin.atlas.min(axis=0), skin.atlas.max(axis=0)
    xs = np.concatenate([rng.uniform(lo[0] - 0.05, hi[0] + 0.05, 400), skin.atlas[:, 0]])
    ys = np.concatenate([rng.uniform(lo[1] - 0.05, hi[1] + 0.05, 400), skin.atlas[:, 1]])
    points = skin.locate(xs, ys)
    charts = skin.chart_at(xs, ys)
    assert len(set(charts.tolist())) > 1  # (the points fall on several charts)
    for x, y, ch, sp in zip(xs, ys, charts, points):
        c = skin.charts[ch]
        px = c.x0 + (x - c.x0) % c.period if c.period > 0 else x
        dx = np.abs(skin.atlas[:, 0] - px)
        if c.period > 0:
            dx = np.minimum(dx, c.period - dx)
        d2 = np.where(skin.chart_of == ch, dx ** 2 + (skin.atlas[:, 1] - y) ** 2, np.inf)
        assert sp.patch == skin.patches[int(skin.patch_of[int(np.argmin(d2))])].name


def _large(links: int, planes: int) -> str:
    """A chain of ``links`` links, and ``planes`` 1x1 patches on its last link, each turned
    about its normal (every one its own chart) 0.1 m from the one before, each a gateway."""
    text = "".join(f'[[link]]\nname = "l{i}"\n' + (f'parent = "l{i - 1}"\n' if i else "") for i in range(links))
    last = f"l{links - 1}"
    text += "".join(f'[[patch]]\nname = "p{i}"\nlink = "{last}"\nshape = "plane"\nrows = 1\ncols = 1\n'
                    f"rpy = [0.0, 0.0, {0.001 * (i + 1)}]\norigin = [{0.1 * i}, 0.0, 0.0]\n" for i in range(planes))
    return text + "".join(f'[[gateway]]\nname = "g{i}"\npatch = "p{i}"\n' for i in range(planes))


@pytest.mark.timeout(60)  # (a guard, not a speed claim: bench/ measures; the pairwise checks took ~52 s)
def test_a_deep_parent_chain_and_many_patches_are_read_in_linear_time() -> None:
    """A chain 10 000 links deep, 1 500 patches each on its own surface of one link, a
    gateway on each: read in seconds (the checks compared every pair: about a minute),
    and whatever walks the links or patches by name stays linear."""
    s = parse_skin(_large(10_000, 1_500), "large.toml")
    assert len(s.charts) == 1_500 and len(s.links) == 10_000
    assert len(s.gateway_ids()) == 1_500
    assert s.link_pose("l9999")[2, 3] == 0.0


def test_more_patches_than_the_limit_are_refused_at_once() -> None:
    """Each patch's surface is looked for among the charts before it: a hostile file of
    65 534 one-element patches, each on its own surface, is refused before that."""
    from cellbridge.tactile.skin_geometry import MAX_PATCHES

    text = _large(1, MAX_PATCHES + 1)
    with pytest.raises(SkinError, match=f"patch: at most {MAX_PATCHES}"):
        parse_skin(text, "many.toml")


def test_a_urdf_joint_that_is_no_rigid_motion_is_refused_naming_the_joint(tmp_path) -> None:
    """A URDF joint's origin becomes a link's pose in topology, Foxglove's transforms and
    ROS 2: a NaN in it, or a translation beyond what the views read, is refused."""
    pytest.importorskip("yourdfpy")
    from cellbridge.daemon.shell.skin_file import load_skin

    skin_text = ('urdf = "arm.urdf"\n[[patch]]\nname = "p"\nlink = "fore"\nshape = "plane"\nrows = 1\ncols = 2\n'
                 '[[gateway]]\nname = "g"\npatch = "p"\n')
    (tmp_path / "skin.toml").write_text(skin_text)
    for xyz, message in (("nan 0 0.3", "not finite"), ("0 0 5000", "must lie within")):
        (tmp_path / "arm.urdf").write_text(f"""<robot name="arm">
  <link name="base"/><link name="fore"/>
  <joint name="elbow" type="fixed"><parent link="base"/><child link="fore"/><origin xyz="{xyz}"/></joint>
</robot>""")
        with pytest.raises(SkinError, match=f"URDF's link 'fore'.*{message}"):
            load_skin(tmp_path / "skin.toml")


def test_a_truncated_urdf_is_refused_not_recovered(tmp_path, capfd) -> None:
    """A URDF cut short (copied while it was being written) is not XML: read with the XML
    parser's recovery, the joint cut off put its link at its parent's origin, 0.3 m from
    where it is, and only a log line said so. Refused, naming the file, nothing printed."""
    pytest.importorskip("yourdfpy")
    from cellbridge.daemon.shell.skin_file import load_skin

    (tmp_path / "skin.toml").write_text('urdf = "arm.urdf"\n[[patch]]\nname = "p"\nlink = "fore"\nshape = "plane"\n'
                                        'rows = 1\ncols = 2\n[[gateway]]\nname = "g"\npatch = "p"\n')
    whole = """<robot name="arm">
  <link name="base"/><link name="fore"/>
  <joint name="elbow" type="fixed"><parent link="base"/><child link="fore"/><origin xyz="0 0 0.3"/></joint>
</robot>"""
    (tmp_path / "arm.urdf").write_text(whole)
    assert load_skin(tmp_path / "skin.toml").link_pose("fore")[2, 3] == pytest.approx(0.3)
    (tmp_path / "arm.urdf").write_text(whole[:whole.index('0.3"') + 3])
    with pytest.raises(SkinError, match="arm.urdf: not a URDF it can read: not well-formed XML"):
        load_skin(tmp_path / "skin.toml")
    # a DTD: entities expanded a billion times, or a file of this machine read into link names
    (tmp_path / "arm.urdf").write_text('<?xml version="1.0"?>\n<!DOCTYPE r [<!ENTITY x SYSTEM "file:///etc/hostname">]>'
                                       + whole.replace('"fore"', '"&x;"'))
    with pytest.raises(SkinError, match="arm.urdf: not a URDF it can read: it declares a DTD"):
        load_skin(tmp_path / "skin.toml")
    out, err = capfd.readouterr()
    assert out == "" and err == ""


_TWO_PLANES = """side = 0.04
[[link]]
name = "box"
[[patch]]
name = "top"
link = "box"
shape = "plane"
rows = 2
cols = 2
[[patch]]
name = "second"
link = "box"
shape = "plane"
rows = 2
cols = 2
{pose}
[[gateway]]
name = "g"
patch = "top"
[[gateway]]
name = "h"
patch = "second"
"""


@pytest.mark.parametrize("pose, overlaps", [
    ("origin = [0.0, 0.0, 0.00001]", True),  # 10 µm off the first one's plane: its own chart, on top of it
    ("rpy = [0.0, 0.0, 0.00001]", True),  # turned a little: its own chart, on top of it
    ("origin = [0.04, 0.0, 0.0]\nrpy = [0.0, 0.0, 0.0001]", True),  # one column overlapping, turned a little
    ("origin = [0.06, 0.0, -0.02]\nrpy = [0.0, 1.5707963267948966, 0.0]", False),  # a box's next face
    ("origin = [0.0, 0.04, -0.001]\nrpy = [3.141592653589793, 0.0, 0.0]", False),  # underneath, facing away
    ("origin = [0.1, 0.0, 0.0]\nrpy = [0.0, 0.0, 0.0001]", False),  # beside it, apart
])
def test_patches_of_one_link_on_top_of_each_other_are_refused(pose, overlaps) -> None:
    """Two patches of one link whose elements lie on top of each other, on surfaces a hair
    apart (so not one chart, where the layout would refuse the overlap): each press there
    read as two contacts at one place. Refused naming both; a fold (a box's faces) is not."""
    text = _TWO_PLANES.format(pose=pose)
    if overlaps:
        with pytest.raises(SkinError, match="patches 'top' and 'second' of link 'box' overlap"):
            parse_skin(text, "box.toml")
    else:
        assert len(parse_skin(text, "box.toml").charts) == 2


def test_a_surface_without_a_gateway_is_refused_naming_the_file_and_its_patches() -> None:
    """Cells join neighbouring elements of one surface only: the chest's patches with no
    gateway of their own reach none. `mesh check`/`mesh up`/`mesh traffic` said "test:
    bridge 22 is unreachable" (the skin's name, a bridge id); now the file and the patches."""
    from cellbridge.emulator.mesh.mesh import MeshError, parse_mesh

    text = SKIN.replace('[[gateway]]\nname = "chest"\npatch = "chest_l"\n', "")
    with pytest.raises(MeshError, match="^arm.toml: patches 'chest_l', 'chest_r' of link 'torso' reach no gateway"):
        parse_mesh(text, "arm.toml")


@pytest.mark.parametrize("body, message", [
    ('<link name="base"/><link name="fore"/><link name="fore"/>'
     '<joint name="elbow" type="fixed"><parent link="base"/><child link="fore"/><origin xyz="0 0 0.3"/></joint>',
     "link 'fore' is described twice"),
    ('<link name="base"/><link name="fore"/>'
     '<joint name="elbow" type="fixed"><parent link="base"/><child link="fore"/><origin xyz="0 0 0.3"/></joint>'
     '<joint name="wrist" type="fixed"><parent link="base"/><child link="fore"/><origin xyz="0 0 0.5"/></joint>',
     "link 'fore' is the child of two joints \\('elbow', 'wrist'\\)"),
])
def test_a_urdf_that_places_a_link_twice_is_refused(tmp_path, body, message) -> None:
    """A link described twice, or the child of two joints: which pose is its? The last
    joint read was taken (0.5 m here, or 0.3), silently; refused naming the link."""
    pytest.importorskip("yourdfpy")
    from cellbridge.daemon.shell.skin_file import load_skin

    (tmp_path / "skin.toml").write_text('urdf = "arm.urdf"\n[[patch]]\nname = "p"\nlink = "fore"\nshape = "plane"\n'
                                        'rows = 1\ncols = 2\n[[gateway]]\nname = "g"\npatch = "p"\n')
    (tmp_path / "arm.urdf").write_text(f'<robot name="arm">{body}</robot>')
    with pytest.raises(SkinError, match=f"arm.urdf: {message}"):
        load_skin(tmp_path / "skin.toml")

"""The views' model of a skin on a robot (cellbridge/views/robot_skin.py, model.py), in
process: the skin drawn patch by patch, a flat skin as before, and every new field from
the daemon (topology's ``skin``, contacts' link, patch, position, normal, force vector)
read defensively: wrong types, NaN, ±inf, poses that are no rigid motion, loops of
links, oversized lists are counted and shown as unknown, never raised."""

from __future__ import annotations

import copy
import math
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import robot_payloads as rp
from cellbridge.views import foxglove as fx
from cellbridge.views.model import SkinView
from cellbridge.views.robot_skin import pack_patches, quat_from_to, rigid, rotate
from fake_daemon import grid_layout


def robot_view(topology: dict[str, Any] | None = None, contact: dict[str, Any] | None = None) -> SkinView:
    sk = rp.skin()
    m = SkinView()
    m.feed("topology", topology if topology is not None else rp.topology(sk), 0.0)
    m.feed("element", rp.element(sk), 0.0)
    m.feed("contact", contact if contact is not None else rp.contact(sk), 0.0)
    return m


def encode_all(m: SkinView) -> None:
    """Every Foxglove message of the model's state can be made and encoded."""
    f = m.frame(0.0)
    frames = fx.link_frames(m.skin) if f.patches else {}
    assert fx.make_transforms(frames, 1).encode() is not None
    assert fx.make_skin_scene(m, frames, 1).encode() is not None
    assert fx.make_scene(m, f, frames, bool(f.patches), 1).encode() is not None
    if not f.patches and f.cells:
        assert fx.make_grid(f, 1).encode()


def test_a_flat_4x4_skin_is_drawn_as_before_one_grid_no_patches() -> None:
    m = SkinView()
    m.feed("topology", {"v": 2, "seq": 0, "layout": grid_layout(4, 4), "skin": None}, 0.0)
    m.feed("element", {"v": 2, "seq": 0, "bridge": [6], "force": [2.0], "valid": [True], "touched": [True]}, 0.0)
    m.feed("contact", {"v": 2, "seq": 0, "contacts": [
        {"id": 3, "x": 0.06, "y": 0.06, "force": 2.0, "diameter": 0.01, "link": None, "patch": None,
         "position": [0.06, 0.06, 0.0], "normal": [0.0, 0.0, 1.0], "force_vector": [0.0, 0.0, -2.0]}]}, 0.0)
    f = m.frame(0.0)
    assert f.patches == [] and (f.rows, f.cols) == (4, 4)
    assert {c.bridge: (c.row, c.col) for c in f.cells} == {b: ((b - 1) // 4, (b - 1) % 4) for b in range(1, 17)}
    (c,) = f.contacts
    assert (c.col, c.row) == pytest.approx((1.5, 1.5))
    assert c.line == "#3  x 60.0 mm  y 60.0 mm  F 2.00 N  ⌀ 10.0 mm"
    assert m.bad_fields == 0 and m.skin is None
    encode_all(m)


def test_the_arm_is_drawn_patch_by_patch_with_its_contacts_on_their_patch() -> None:
    m = robot_view()
    f = m.frame(0.0)
    assert [b.title for b in f.patches] == ["torso / chest_left", "torso / chest_right",
                                            "upper_arm / upper_low (around)", "upper_arm / upper_high (around)",
                                            "forearm / forearm (around)"]
    assert m.bad_fields == 0
    sk = rp.skin()
    at = {b.name: b for b in f.patches}
    cells = {c.bridge: c for c in f.cells}
    for k, b in enumerate(sk.ids.tolist()):
        p = sk.patches[int(sk.patch_of[k])]
        assert (cells[b].row, cells[b].col) == (at[p.name].row0 + int(sk.row[k]), at[p.name].col0 + int(sk.col[k]))
    for con in f.contacts:
        pname, r, c, force, d, dx = rp.PRESSES[con.id - 7]
        assert con.col == pytest.approx(at[pname].col0 + c + 0.5 + dx / sk.patch(pname).col_pitch)
        assert con.row == pytest.approx(at[pname].row0 + r + 0.5)
    assert "skin: arm, 45 elements in 5 patches on 3 links" in f.status
    encode_all(m)


def test_a_contact_across_a_wrap_seam_is_drawn_inside_its_patch() -> None:
    sk = rp.skin()
    contact = rp.contact(sk)
    first = sk.atlas[sk.row_of(sk.element_id("forearm", 0, 0))]
    contact["contacts"][0].update(x=float(first[0]) - 0.03, y=float(first[1]))  # left of column 0: past the seam
    f = robot_view(contact=contact).frame(0.0)
    blk = next(b for b in f.patches if b.name == "forearm")
    con = next(c for c in f.contacts if c.id == 7)
    assert blk.col0 <= con.col < blk.col0 + blk.cols
    assert con.col > blk.col0 + blk.cols - 1  # in the last column, next to the seam


def test_patches_do_not_overlap_and_leave_a_title_row() -> None:
    sk = rp.skin()
    m = robot_view()
    blocks, rows, cols = pack_patches(list(m.skin.patches.values()))  # type: ignore[union-attr]
    taken: set[tuple[int, int]] = set()
    for b in blocks:
        mine = {(b.row0 + r, b.col0 + c) for r in range(b.rows + 1) for c in range(b.cols)}  # with its title row
        assert not mine & taken
        taken |= mine
        assert 0 <= b.row0 and b.row0 + b.rows < rows and b.col0 + b.cols <= cols
    assert len(blocks) == len(sk.patches)


HOSTILE = [math.nan, math.inf, -math.inf, 1e308, "x", None, True, [], {}, [1, 2], [[1, 2, 3, 4]] * 4, -1, 2**70]


@pytest.mark.parametrize("bad", HOSTILE, ids=repr)
@pytest.mark.parametrize("where", ["links", "origin", "parent", "patches", "rows", "shape", "elements", "ids",
                                   "position", "normal", "row", "patch", "skin"])
def test_unreadable_skin_fields_are_counted_and_shown_as_unknown(where: str, bad: Any) -> None:
    topo = rp.topology(rp.skin())
    sk = topo["skin"]
    if where == "skin":
        topo["skin"] = bad
    elif where in ("links", "patches", "elements"):
        sk[where] = bad
    elif where in ("origin", "parent"):
        sk["links"][1][where] = bad
    elif where in ("rows", "shape"):
        sk["patches"][4][where] = bad
    else:
        col = sk["elements"][where]
        col[3] = bad
        col[40] = bad
    m = robot_view(topology=topo)
    f = m.frame(0.0)
    assert f.cells and all(c.bridge for c in f.cells)
    encode_all(m)
    if where == "origin" and bad != [[1, 2, 3, 4]] * 4:
        assert "upper_arm" not in fx.link_frames(m.skin) and "forearm" not in fx.link_frames(m.skin)
        assert m.bad_fields > 0
    if where == "parent" and bad is not None:  # a mistyped parent: no root, no frame
        assert "upper_arm" not in fx.link_frames(m.skin) and m.bad_fields > 0
    if where in ("position", "normal") and bad is not None:
        assert m.bad_fields > 0


def test_loops_of_links_a_link_named_like_the_root_frame_and_a_scaled_pose_get_no_frame() -> None:
    topo = rp.topology(rp.skin())
    links = topo["skin"]["links"]
    links[1]["parent"] = "forearm"  # upper_arm <- forearm <- upper_arm: a loop
    links[0]["origin"] = [[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]]  # scaled: no rigid motion
    links.append({"name": "skin", "parent": None, "origin": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]})
    m = robot_view(topology=topo)
    assert fx.link_frames(m.skin) == {}
    encode_all(m)
    assert m.bad_fields >= 1


@pytest.mark.parametrize("field,bad", [("position", [math.nan, 0, 0]), ("position", "x"), ("position", [1, 2]),
                                       ("normal", [0, 0, 0]), ("force_vector", [math.inf, 0, 0]),
                                       ("link", 5), ("patch", ["x"]), ("position", [1e308, 0, 0])])
def test_unreadable_contact_fields_are_counted_and_the_contact_not_drawn_in_3d(field: str, bad: Any) -> None:
    sk = rp.skin()
    contact = rp.contact(sk)
    contact["contacts"][0][field] = bad
    m = robot_view(contact=contact)
    assert m.bad_fields == 1
    c = next(c for c in m.contacts if c.id == 7)
    assert getattr(c, field) is None
    f = m.frame(0.0)
    scene = fx.make_scene(m, f, fx.link_frames(m.skin), True, 1)
    assert scene.encode() is not None
    assert next(x for x in f.contacts if x.id == 7).line.startswith("#7")


def test_names_with_control_characters_are_shown_escaped() -> None:
    topo = rp.topology(rp.skin())
    for p in topo["skin"]["patches"]:
        p["link"] = "\x1b]52;c;cHduZWQ=\x07" + p["link"]
    for ln in topo["skin"]["links"]:
        ln["name"] = "\x1b]52;c;cHduZWQ=\x07" + ln["name"]
        if ln["parent"]:
            ln["parent"] = "\x1b]52;c;cHduZWQ=\x07" + ln["parent"]
    contact = copy.deepcopy(rp.contact(rp.skin()))
    contact["contacts"][0]["link"] = "\x1b[31m" + contact["contacts"][0]["link"]
    f = robot_view(topology=topo, contact=contact).frame(0.0)
    assert all("\x1b" not in b.title and "\\x1b]52" in b.title for b in f.patches)
    assert all("\x1b" not in c.line for c in f.contacts)


unit = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: 1e-3 < math.sqrt(sum(x * x for x in v)))


def _norm(v: tuple[float, float, float]) -> tuple[float, float, float]:
    n = math.sqrt(sum(x * x for x in v))
    return (v[0] / n, v[1] / n, v[2] / n)


@settings(max_examples=300, deadline=None)
@given(unit, unit)
def test_quat_from_to_turns_one_direction_onto_the_other(a: Any, b: Any) -> None:
    a, b = _norm(a), _norm(b)
    q = quat_from_to(a, b)
    assert math.isclose(sum(x * x for x in q), 1.0, abs_tol=1e-9)
    assert all(math.isclose(x, y, abs_tol=1e-6) for x, y in zip(rotate(q, a), b))


@settings(max_examples=300, deadline=None)
@given(st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: sum(x * x for x in q) > 1e-2),
       st.tuples(*[st.floats(-10, 10)] * 3))
def test_rigid_reads_back_the_rotation_and_translation_of_a_pose(q: Any, t: Any) -> None:
    n = math.sqrt(sum(x * x for x in q))
    x, y, z, w = (c / n for c in q)
    cols = [rotate((x, y, z, w), e) for e in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))]
    m = [[cols[0][i], cols[1][i], cols[2][i], t[i]] for i in range(3)] + [[0.0, 0.0, 0.0, 1.0]]
    got = rigid(m)
    assert got is not None
    assert all(math.isclose(a, b, abs_tol=1e-9) for a, b in zip(got[0], t))
    for e in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.3, -0.5, 0.8)):
        assert all(math.isclose(a, b, abs_tol=1e-6) for a, b in zip(rotate(got[1], e), rotate((x, y, z, w), e)))
    mirrored = [[-r[0], r[1], r[2], r[3]] for r in m[:3]] + [m[3]]
    assert rigid(mirrored) is None  # a reflection is no pose


def test_the_terminal_grid_titles_each_patch_and_keeps_the_names_of_narrow_ones_apart() -> None:
    from cellbridge.views import textgrid

    text = textgrid.layout(robot_view().frame(0.0), 80, 16).text()
    assert "chest_left" in text[0] and "chest_right" in text[0] and "upper_arm / upper_low (around)" in text[0]
    assert any("forearm / forearm (around)" in line for line in text)
    assert any("●7" in line for line in text) and any("●8" in line for line in text)


def test_patches_too_large_for_the_grid_are_drawn_as_the_layouts_plane_and_said_so() -> None:
    topo = rp.topology(rp.skin())
    for p in topo["skin"]["patches"]:
        p["cols"] = 100  # five patches 100 columns wide: no two side by side within 128
        p["rows"] = 100
    f = robot_view(topology=topo).frame(0.0)
    assert f.patches == [] and len(f.cells) == 45
    assert any(line.endswith("(drawn as the layout's plane)") for line in f.status)


json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
                           lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=8), inner,
                                                                                        max_size=5), max_leaves=30)
skin_keys = st.sampled_from(["links", "patches", "elements", "name", "origin", "parent", "rows", "cols", "ids",
                             "patch", "row", "col", "position", "normal", "link", "wrap", "pitch", "col_pitch"])


@settings(max_examples=400, deadline=None)
@given(st.dictionaries(skin_keys, json_values, max_size=6), st.integers(0, 4), skin_keys, json_values)
def test_any_skin_map_is_read_without_raising(extra: dict[str, Any], k: int, key: str, value: Any) -> None:
    """Any msgpack-like value anywhere in a skin map: read, frame drawn, Foxglove messages encoded."""
    topo = rp.topology(rp.skin())
    sk = topo["skin"]
    sk.update(extra)
    for part in ("links", "patches"):
        if isinstance(sk.get(part), list) and sk[part]:
            item = sk[part][k % len(sk[part])]
            if isinstance(item, dict):
                item[key] = value
    m = robot_view(topology=topo)
    encode_all(m)
    m.frame(0.0)


def test_a_flat_skins_contact_arrow_points_into_the_skin() -> None:
    m = SkinView()
    m.feed("topology", {"v": 2, "seq": 0, "layout": grid_layout(3, 3), "skin": None}, 0.0)
    m.feed("contact", {"v": 2, "seq": 0, "contacts": [{"id": 1, "x": 0.06, "y": 0.06, "force": 2.0, "diameter": 0.01}]},
           0.0)
    msg = decode_scene(fx.make_scene(m, m.frame(0.0), {}, False, 1))
    (e,) = msg.entities
    (arrow,) = e.arrows
    q = (arrow.pose.orientation.x, arrow.pose.orientation.y, arrow.pose.orientation.z, arrow.pose.orientation.w)
    d = rotate(q, (1.0, 0.0, 0.0))
    assert e.frame_id == "skin" and all(math.isclose(a, b, abs_tol=1e-9) for a, b in zip(d, (0.0, 0.0, -1.0)))
    tip_z = arrow.pose.position.z - (arrow.shaft_length + arrow.head_length)
    assert 0.0 < tip_z < 0.005 and arrow.pose.position.x == pytest.approx(0.06)


def decode_scene(scene: Any) -> Any:
    """A SceneUpdate as a client decodes it, with the schema the SDK advertises."""
    from foxglove.messages import SceneUpdate
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(SceneUpdate.get_schema().data)
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("foxglove.SceneUpdate")).FromString(scene.encode())


def test_an_update_of_changed_patches_replaces_only_their_entities_and_deletes_nothing() -> None:
    m = robot_view()
    frames = fx.link_frames(m.skin)
    whole = decode_scene(fx.make_skin_scene(m, frames, 1))
    assert len(whole.deletions) == 1 and len(whole.entities) == 5
    part = decode_scene(fx.make_skin_scene(m, frames, 1, only={"forearm"}))
    assert len(part.deletions) == 0 and [e.id for e in part.entities] == ["patch-forearm"]
    before = fx.patch_colours(m)
    sk = rp.skin()
    m.feed("element", {"v": 2, "seq": 1, "source": rp.SOURCE, "bridge": [sk.element_id("chest_left", 0, 0)], "force": [4.0], "valid": [True],
                       "touched": [True]}, 0.0)
    after = fx.patch_colours(m)
    assert {n for n in after if after[n] != before[n]} == {"chest_left"}


@pytest.mark.parametrize("side", [5e-324, 1e-300])
def test_a_tiny_element_side_does_not_overflow_the_contacts_placing(side: float) -> None:
    """Found by the fuzz test: the layout's cell of a contact, x / side, was inf (OverflowError)."""
    topo = rp.topology(rp.skin())
    topo["layout"]["side"] = side
    contact = rp.contact(rp.skin())
    for c in contact["contacts"]:
        c["patch"] = None  # placed by the nearest element
    m = robot_view(topology=topo, contact=contact)
    f = m.frame(0.0)
    assert len(f.contacts) == 2
    encode_all(m)


def _drawn(contact: dict[str, Any]) -> tuple[Any, Any]:
    f = robot_view(contact=contact).frame(0.0)
    return f, next(c for c in f.contacts if c.id == 7)


def _on_a_block(f: Any, con: Any) -> str | None:
    """The patch whose block the drawn contact lies on (a cell's margin around it), or None."""
    for b in f.patches:
        if b.col0 - 1 <= con.col <= b.col0 + b.cols + 1 and b.row0 - 1 <= con.row <= b.row0 + b.rows + 1:
            return b.name
    return None


@pytest.mark.parametrize("link, patch", [("ghost", "ghost_patch"), ("ghost", None), ("torso", None),
                                         ("torso", "forearm"), (None, "ghost_patch")])
def test_a_contact_on_a_link_or_patch_the_topology_contradicts_is_listed_not_drawn_on_another_patch(
        link: Any, patch: Any) -> None:
    """Contact 7 lies on the forearm's atlas place; it names a link not in the topology,
    or the torso (whose patches are elsewhere), or a patch of another link: the flat
    views must not draw it on the forearm's (or any) block as if it were there."""
    contact = rp.contact(rp.skin())
    contact["contacts"][0].update(link=link, patch=patch)
    f, con = _drawn(contact)
    assert _on_a_block(f, con) is None, (con.col, con.row, _on_a_block(f, con))
    assert math.isnan(con.col) and math.isnan(con.row)
    assert con.line.startswith("#7")  # still listed


def test_a_contact_far_off_its_patch_is_not_drawn_on_another_patchs_block() -> None:
    """Contact 7 names the forearm but its atlas place is on the chest: drawn by the
    forearm's affine map it would land beyond the forearm's block, on another's."""
    sk = rp.skin()
    contact = rp.contact(sk)
    far = sk.atlas[sk.row_of(sk.element_id("chest_left", 0, 0))]
    contact["contacts"][0].update(x=float(far[0]), y=float(far[1]))
    f, con = _drawn(contact)
    assert _on_a_block(f, con) in (None, "forearm"), (con.col, con.row, _on_a_block(f, con))


@pytest.mark.parametrize("link, patch", [("torso", "forearm"), ("forearm", "ghost_patch"), ("ghost", None)])
def test_foxglove_draws_no_contact_whose_patch_the_topology_puts_on_another_link_or_lacks(link: str, patch: Any) -> None:
    """Contact 7 at its forearm position, said to be on the torso's frame with the forearm's
    patch (or on a patch the topology lacks, or on a link it lacks): where it is is
    contradicted, so it is not drawn at that position in some link's frame."""
    contact = rp.contact(rp.skin())
    contact["contacts"][0].update(link=link, patch=patch)
    m = robot_view(contact=contact)
    f = m.frame(0.0)
    scene = decode_scene(fx.make_scene(m, f, fx.link_frames(m.skin), True, 1))
    ids = {e.id for e in scene.entities}
    assert "contact-7" not in ids and "contact-8" in ids, ids

"""The ROS 2 side's core, without processes: the shipped definitions, the converter's messages."""

from __future__ import annotations

import math
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("cyclonedds", reason="the ros2 extra is not installed (make install installs it)")

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from cellbridge.ros2 import msgdefs
from cellbridge.ros2 import types as T
from cellbridge.ros2.convert import Converter
from cellbridge.ros2.qos import BadTopicName, topics
from ros2_peer import typestore

LAYOUT = {"layout": {"ids": [1, 2, 3, 4], "x": [0.02, 0.06, 0.02, 0.06], "y": [0.02, 0.02, 0.06, 0.06], "side": 0.04}}


def element(**cols: Any) -> dict[str, Any]:
    base = {"v": 1, "seq": 0, "t_host": 1.7e9, "bridge": [1, 2, 3], "force": [2.0, math.nan, math.nan],
            "area": [1e-4, math.nan, math.nan], "dc1": [1e-12, 2e-14, math.nan], "dc2": [5e-13, 1e-14, math.nan],
            "valid": [True, False, False], "status": [0, 2, 8], "touched": [True, False, True],
            "t_sample": [1.7e9 - 0.01, 1.7e9 - 0.02, math.nan]}
    return {**base, **cols}


def test_the_standard_definitions_are_ros_2_humbles_and_jazzys_field_for_field() -> None:
    for store in (get_typestore(Stores.ROS2_HUMBLE), get_typestore(Stores.ROS2_JAZZY)):
        for name in msgdefs.shipped():
            if name.startswith("tactile_msgs/"):
                continue
            ours = get_types_from_msg(msgdefs.text(name), name)[name]  # our shipped text, parsed
            assert store.fielddefs[name][1] == ours[1], name
    # a schema lists every type the message uses, each once, as rosbag2 does
    schema = msgdefs.schema("visualization_msgs/msg/MarkerArray")
    rosbags_text, _ = get_typestore(Stores.ROS2_HUMBLE).generate_msgdef("visualization_msgs/msg/MarkerArray",
                                                                       ros_version=2)
    deps = [line for line in schema.splitlines() if line.startswith("MSG: ")]
    assert deps == [line for line in rosbags_text.splitlines() if line.startswith("MSG: ")]


def test_the_tactile_definitions_are_tactile_toolboxs_fields() -> None:
    fields = {n: [(f, str(node)) for f, node in typestore().fielddefs[n][1]] for n in msgdefs.shipped()
              if n.startswith("tactile_msgs/")}
    assert [f for f, _ in fields["tactile_msgs/msg/TactileState"]] == ["header", "sensors"]
    assert [f for f, _ in fields["tactile_msgs/msg/TactileContact"]] == ["header", "name", "position", "normal",
                                                                         "wrench"]
    assert [f for f, _ in fields["tactile_msgs/msg/TactileContacts"]] == ["contacts"]
    assert "sensor_msgs/msg/ChannelFloat32" in fields["tactile_msgs/msg/TactileState"][1][1]


def test_readings_untouched_read_zero_unknown_read_nan_in_element_order() -> None:
    c = Converter()
    c.set_layout(LAYOUT)
    (key, state), *_ = c.feed("element", element(), 0.0)
    assert key == "state" and state.header.frame_id == "cellbridge_skin"
    ch = {s.name: s.values for s in state.sensors}
    assert ch["cellbridge_skin/element"] == [1.0, 2.0, 3.0, 4.0]
    assert ch["cellbridge_skin"][:2] == [2.0, 0.0]  # bridge 2: untouched (status 2), 0 N
    assert math.isnan(ch["cellbridge_skin"][2]) and math.isnan(ch["cellbridge_skin"][3])  # ambiguous; never read
    assert ch["cellbridge_skin/dc1"][:2] == [1e-12, 2e-14]
    assert T.stamp(1.7e9 - 0.01) == state.header.stamp  # the newest sample


def test_a_contact_is_a_tactile_contact_with_the_wrench_into_the_skin() -> None:
    c = Converter(frame_id="palm")
    c.set_layout(LAYOUT)
    contacts = {"t_sample": 1.7e9, "t_host": 1.7e9 + 0.01, "contacts": [
        {"id": 7, "x": 0.04, "y": 0.05, "force": 3.0, "valid": True, "diameter": 0.02, "observable": [True, False]},
        {"id": 8, "x": 0.01, "y": 0.01, "force": 0.5, "valid": False},
        {"id": 9, "x": 0.1, "y": 0.1, "force": 1.0, "link": "forearm"}]}
    out = dict(c.feed("contact", contacts, 0.0))
    a, b, d = out["contacts"].contacts
    assert a.name == "contact_7" and a.header.frame_id == "palm" and a.header.stamp == T.stamp(1.7e9)
    assert (a.position.x, a.position.y, a.position.z) == (0.04, 0.05, 0.0)
    assert (a.wrench.force.x, a.wrench.force.y, a.wrench.force.z) == (0.0, 0.0, -3.0)
    assert (a.wrench.torque.x, a.wrench.torque.y, a.wrench.torque.z) == pytest.approx((-0.15, 0.12, 0.0))
    assert math.isnan(b.wrench.force.z)  # no pressure: the force is not known
    assert d.header.frame_id == "forearm"
    labels = [m.text for m in out["markers"].markers if m.ns == "labels"]
    assert any("y ~50.0" in t and "unresolved" in t for t in labels), labels
    # the contacts end: an empty list, and the picture loses them at once
    out = dict(c.feed("contact", {"t_sample": 1.7e9 + 1, "contacts": []}, 0.001))
    assert out["contacts"].contacts == [] and not [m for m in out["markers"].markers if m.ns == "contacts"]


def test_a_contact_on_a_link_is_at_its_position_in_that_link_frame_pressing_along_its_normal() -> None:
    # a robot skin's contact: x, y are its place on the unrolled patches (the atlas), not
    # link coordinates; its point, normal and force in the link frame are position, normal
    c = Converter()
    c.set_layout(LAYOUT)
    p, n = [0.3, -0.02, 0.05], [0.0, -1.0, 0.0]
    contact: dict[str, object] = {"id": 4, "x": 0.12, "y": 0.7, "force": 2.0, "valid": True, "diameter": 0.02,
                                  "link": "forearm", "position": p, "normal": n, "force_vector": [0.0, 2.0, 0.0]}
    contacts = {"t_sample": 1.7e9, "contacts": [contact]}
    out = dict(c.feed("contact", contacts, 0.0))
    (a,) = out["contacts"].contacts
    assert a.header.frame_id == "forearm"
    assert (a.position.x, a.position.y, a.position.z) == tuple(p)
    assert (a.normal.x, a.normal.y, a.normal.z) == tuple(n)
    assert (a.wrench.force.x, a.wrench.force.y, a.wrench.force.z) == (0.0, 2.0, 0.0)
    # torque about the link frame's origin: position x force
    assert (a.wrench.torque.x, a.wrench.torque.y, a.wrench.torque.z) == pytest.approx((-0.1, 0.0, 0.6))
    marks = {m.ns: m for m in out["markers"].markers if m.ns in ("contacts", "forces", "labels")}
    assert all(m.header.frame_id == "forearm" for m in marks.values())
    disk = marks["contacts"].pose
    # the disk lies on the surface at the point, its axis along the normal (z turned onto -y)
    assert (disk.position.x, disk.position.y, disk.position.z) == pytest.approx((0.3, -0.022, 0.05))
    q = disk.orientation
    axis_z = (2 * (q.x * q.z + q.w * q.y), 2 * (q.y * q.z - q.w * q.x), 1 - 2 * (q.x * q.x + q.y * q.y))
    assert axis_z == pytest.approx(tuple(n), abs=1e-9)
    tail, head = marks["forces"].points
    assert (head.x, head.y, head.z) == pytest.approx((0.3, -0.024, 0.05))  # it ends at the skin, pressing in
    assert (tail.x - head.x, tail.y - head.y, tail.z - head.z) == pytest.approx((0.0, -0.02, 0.0))  # 1 cm a N
    lab = marks["labels"].pose.position
    assert (lab.x, lab.y, lab.z) == pytest.approx((0.3, -0.04, 0.05))
    # a position the daemon did not send whole or finite is the atlas place on the plane
    contact.update(position=[0.3, None, 0.05], link=None, normal=None)
    ((_, got), *_) = c.feed("contact", contacts, 1.0)
    (a,) = got.contacts
    assert (a.position.x, a.position.y, a.position.z) == (0.12, 0.7, 0.0)


def test_health_becomes_diagnostics_with_a_level_that_says_what_is_wrong() -> None:
    c = Converter()
    health = {"t_host": 1.7e9, "source": "robot", "links": {"gw": {"connected": False, "last_error": "gone"}},
              "bridges": {"1": {"silent": True, "age": 3.0}, "2": {"loss": 0.2}, "3": {"loss": 0.0}}}
    ((key, diag),) = c.feed("health", health, 0.0)
    s = {x.name: x for x in diag.status}
    assert s["cellbridge: daemon"].level == T.DiagnosticStatus.ERROR and s["cellbridge: daemon"].hardware_id == "robot"
    assert s["cellbridge: link gw"].level == T.DiagnosticStatus.ERROR and "gone" in s["cellbridge: link gw"].message
    assert [s[f"cellbridge: bridge {b}"].level for b in (1, 2, 3)] == [2, 1, 0]


payloads = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
                        lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                                    max_size=5), max_leaves=20)


@settings(max_examples=300, deadline=None)
@given(topic=st.sampled_from(["element", "contact", "health", "topology", "raw"]),
       payload=payloads | st.fixed_dictionaries({"bridge": payloads, "contacts": payloads, "layout": payloads,
                                                 "links": payloads, "bridges": payloads}))
def test_no_payload_makes_the_converter_raise_or_a_message_that_does_not_serialise(topic: str, payload: Any) -> None:
    c = Converter(marker_period=0)
    c.set_layout(LAYOUT)
    for _, message in c.feed(topic, payload, 0.0):
        T.cdr(message)


def test_topic_names_are_checked() -> None:
    assert topics("/left/skin")["contacts"].dds_name == "rt/left/skin/contacts"
    for bad in ("left", "/", "/a//b", "/1a", "/a b", "/a__b"):
        with pytest.raises(BadTopicName):
            topics(bad)


def test_diagnostics_at_most_once_a_period_but_at_once_when_the_daemons_level_changes() -> None:
    c = Converter(diagnostics_period=1.0)
    ok = {"t_host": 1.7e9, "links": {"gw": {"connected": True}}, "bridges": {"1": {"loss": 0.0}}}
    down = {"t_host": 1.7e9, "links": {"gw": {"connected": False}}, "bridges": {"1": {"loss": 0.0}}}
    fed = [(0.0, ok), (0.25, ok), (0.5, ok), (0.75, down), (1.0, down), (1.5, ok), (1.75, ok), (2.5, ok)]
    published = [t for t, p in fed if c.feed("health", p, t)]
    assert published == [0.0, 0.75, 1.5, 2.5]  # the period, and the level's two changes at once
    assert c.diagnostics_skipped == len(fed) - len(published)
    assert [key for key, _ in Converter().feed("health", ok, 0.0)] == ["diagnostics"]  # by default: every one


ON_LINK: dict[str, Any] = {"id": 4, "x": 0.12, "y": 0.7, "force": 2.0, "valid": True, "diameter": 0.02,
                           "link": "forearm", "patch": "fa", "position": [0.3, -0.02, 0.05],
                           "normal": [0.0, -1.0, 0.0], "force_vector": [0.0, 2.0, 0.0]}


def _drawn(out: dict[str, Any]) -> dict[str, Any]:
    return {m.ns: m for m in out["markers"].markers if m.ns in ("contacts", "forces", "labels")}


@pytest.mark.parametrize("position", [None, [0.3, -0.02], [0.3, -0.02, 0.05, 1.0], [0.3, math.nan, 0.05],
                                      [0.3, math.inf, 0.05], ["0.3", -0.02, 0.05], [True, -0.02, 0.05], "abc",
                                      [0.3, -0.02, 1e300]])
def test_a_contact_on_a_link_whose_position_is_not_whole_is_nowhere_not_at_its_atlas_place(position: Any) -> None:
    # x, y are the place on the unrolled patches: put in the link's frame they are a
    # confident wrong point; the contact is listed (its id, force) with its place unknown
    c = Converter()
    c.set_layout(LAYOUT)
    contact = {**ON_LINK, "position": position}
    if position is None:
        del contact["position"]
    out = dict(c.feed("contact", {"t_sample": 1.7e9, "contacts": [contact]}, 0.0))
    (a,) = out["contacts"].contacts
    assert a.name == "contact_4" and a.header.frame_id == "forearm"
    assert all(math.isnan(v) for v in (a.position.x, a.position.y, a.position.z))
    assert all(math.isnan(v) for v in (a.wrench.torque.x, a.wrench.torque.y, a.wrench.torque.z))
    assert not _drawn(out)  # nothing drawn where it is not known (as the Foxglove scene does)
    assert c.malformed == 1


@pytest.mark.parametrize("normal", [None, [0.0, 0.0, 0.0], [0.0, math.nan, 0.0], [0.0, -1.0], [0.0, -1.0, 0.0, 0.0],
                                    [False, True, False], [1e-300, 0.0, 0.0], "up"])
def test_a_contact_on_a_link_without_a_usable_normal_has_no_direction_not_the_planes(normal: Any) -> None:
    # +z of a link frame is no direction of its skin: the normal and the force along it are unknown
    c = Converter()
    c.set_layout(LAYOUT)
    contact = {**ON_LINK, "normal": normal}
    out = dict(c.feed("contact", {"t_sample": 1.7e9, "contacts": [contact]}, 0.0))
    (a,) = out["contacts"].contacts
    assert (a.position.x, a.position.y, a.position.z) == (0.3, -0.02, 0.05)
    assert all(math.isnan(v) for v in (a.normal.x, a.normal.y, a.normal.z))
    assert all(math.isnan(v) for v in (a.wrench.force.x, a.wrench.force.y, a.wrench.force.z))
    assert not _drawn(out)


def test_a_non_unit_normal_is_normalised_and_the_disk_quaternion_is_unit() -> None:
    c = Converter(marker_period=0)
    c.set_layout(LAYOUT)
    for n in ([0.0, -5.0, 0.0], [1e-6, 0.0, -3.0], [0.0, 1e-12, -1.0], [3.0, 4.0, 0.0]):
        out = dict(c.feed("contact", {"t_sample": 1.7e9, "contacts": [{**ON_LINK, "normal": n}]}, 0.0))
        (a,) = out["contacts"].contacts
        size = math.sqrt(sum(v * v for v in n))
        assert (a.normal.x, a.normal.y, a.normal.z) == pytest.approx(tuple(v / size for v in n))
        q = _drawn(out)["contacts"].pose.orientation
        assert q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2 == pytest.approx(1.0)
        axis_z = (2 * (q.x * q.z + q.w * q.y), 2 * (q.y * q.z - q.w * q.x), 1 - 2 * (q.x * q.x + q.y * q.y))
        assert axis_z == pytest.approx((a.normal.x, a.normal.y, a.normal.z), abs=1e-6)


def test_a_contact_on_a_link_is_labelled_with_its_link_and_place_as_the_views_label_it() -> None:
    from cellbridge.views.model import SkinView, contact_line
    c = Converter()
    c.set_layout(LAYOUT)
    payload = {"t_sample": 1.7e9, "contacts": [ON_LINK]}
    view = SkinView()
    view.feed("contact", payload, 0.0)
    label = _drawn(dict(c.feed("contact", payload, 0.0)))["labels"].text
    assert label == contact_line(view.contacts[0])
    assert "forearm/fa" in label and "(300.0, -20.0, 50.0) mm" in label


@pytest.mark.parametrize("cid", [2**31 - 1, 2**31, 2**40, 2**64])
def test_a_contact_id_past_a_markers_int32_still_serialises(cid: int) -> None:
    # a marker's id is an int32: a daemon's contact id past it must not stop the bridge or the bag
    c = Converter()
    c.set_layout(LAYOUT)
    out = dict(c.feed("contact", {"t_sample": 1.7e9, "contacts": [{**ON_LINK, "id": cid}]}, 0.0))
    assert out["contacts"].contacts[0].name == f"contact_{cid}"
    for message in out.values():
        T.cdr(message)
    assert {m.id for m in _drawn(out).values()} and all(0 <= m.id < 2**31 for m in _drawn(out).values())


def test_the_ros_2_markers_and_the_foxglove_scene_put_a_contact_at_the_same_place() -> None:
    from cellbridge.views.foxglove import contact_place
    from cellbridge.views.model import SkinView
    frames = {"forearm": ("world", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))}
    cases = [ON_LINK, {**ON_LINK, "normal": [0.0, -2.0, 0.0]}, {**ON_LINK, "position": [0.3, -0.02]},
             {**ON_LINK, "normal": [0.0, 0.0, 0.0]}, {**ON_LINK, "position": [2e3, 0.0, 0.0]},
             {**ON_LINK, "normal": [1e7, 0.0, 0.0]}, {**ON_LINK, "position": [True, 0.0, 0.0]}]
    for contact in cases:
        c = Converter()
        c.set_layout(LAYOUT)
        payload = {"t_sample": 1.7e9, "contacts": [contact]}
        view = SkinView()
        view.feed("contact", payload, 0.0)
        fox = contact_place(view.contacts[0], frames, robot=True)
        drawn = _drawn(dict(c.feed("contact", payload, 0.0)))
        if fox is None:
            assert not drawn, contact
            continue
        frame, p, n = fox
        disk = drawn["contacts"]
        assert disk.header.frame_id == frame
        lift = 0.002
        assert (disk.pose.position.x, disk.pose.position.y, disk.pose.position.z) == \
            pytest.approx(tuple(pv + lift * nv for pv, nv in zip(p, n)))

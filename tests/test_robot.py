"""The simulated robot as the world: MuJoCo's contacts on the arm's skin, the daemon's core
estimating them in virtual time, the scores against the ground truth (a short version of
bench/bench_robot.py), and the scorer and the URDF link frames on their own."""

from __future__ import annotations

import math

import numpy as np
import pytest
from cellbridge.tactile.skin_geometry import parse_skin

from cellbridge.robot_score import score

ARM = None


def _arm():
    from cellbridge.emulator.world.robot_world import arm_skin
    return arm_skin()


def test_the_scenario_scores_within_the_targets() -> None:
    pytest.importorskip("mujoco")
    from cellbridge.robot import run_scenario

    s, fig = run_scenario(6, seed=0, idle=1.0)
    kinds = {k for k, (n, _) in s.by_kind.items() if n}
    assert {"single", "wrap", "patch_seam", "slide", "two"} <= kinds
    assert s.truths >= 7 and s.detected == s.truths, s.table()
    assert max(s.ids_per_truth) == 1, s.table()  # one id per contact, seams and slides included
    assert max(s.truths_per_id.values()) == 1, s.table()  # and one contact per id
    assert s.off_truth == 0 and s.not_scored == 0, s.table()  # no report lingers past its press
    assert s.inside_untrue == 0 and all(e <= 2 * sg for e, sg in s.inside), s.table()  # axes inside an element
    assert not s.false_ids and fig["idle_false_contacts"] == 0, s.table()
    # Straddled axes the readings resolve are within the targets, and none states a wrong
    # position; a footprint that reaches only a few mm onto a neighbour leaves it under its
    # touch threshold, and that axis is said unobservable with a σ that covers the truth.
    # (The straddled p95 over both kinds is the bench's row: such axes report the element's
    # middle, up to ~12 mm off, honestly.)
    assert len(s.resolved) > 50 and np.median(s.resolved) <= 2e-3 and np.percentile(s.resolved, 95) <= 5e-3, s.table()
    assert s.untrue == 0, s.table()
    assert all(e <= 2 * sg for e, sg in s.unresolved), s.table()
    assert np.median(s.position) <= 2e-3, s.table()
    assert np.median(s.force) <= 0.03, s.table()


def test_the_truth_follows_the_finger_onto_the_link_it_touched() -> None:
    pytest.importorskip("mujoco")
    from cellbridge.emulator.world.robot_world import Press, simulate

    skin = _arm()
    band = next(b for b in skin.bands if b.period > 0.28)  # the forearm
    press = Press(0, 0.2, band.x0 + 0.002, band.y0 + 0.06, 3.0, 0.02, 0.3)  # across its wrap seam
    tl = simulate(skin, [press], 0.8)
    (tr,) = tl.truths
    assert tr.link == "forearm" and tr.start == pytest.approx(0.2, abs=0.03) and tr.end == pytest.approx(0.6, abs=0.03)
    mid = len(tr.t) // 2
    assert tr.force[mid] == pytest.approx(3.0, rel=0.02)
    x, y = tr.atlas[mid]
    assert abs(((x - press.x) + band.period / 2) % band.period - band.period / 2) < 1e-3 and y == pytest.approx(press.y, abs=1e-3)
    (sp,) = skin.locate([press.x], [press.y])
    assert np.linalg.norm(np.array(tr.point[mid]) - sp.position) < 1e-3
    # the disks on the atlas: the press and its copy one period over, where the world presses both ends
    assert any(len(d) == 1 for d in tl.disks) and tl.at(0.45)[0][2] == pytest.approx(3.0, rel=0.02)


def test_the_scorer_counts_misses_false_contacts_and_errors() -> None:
    skin = _arm()
    (sp,) = skin.locate([0.08], [0.06])  # the torso, on the seam of its two patches (link y)
    truth = {"finger": 0, "link": "torso", "kind": "single", "area": 3e-4, "pad": 0.02, "start": 1.0, "end": 2.0,
             "t": [1.0 + 0.001 * k for k in range(1001)], "point": [sp.position] * 1001,
             "normal": [sp.normal] * 1001, "force": [2.0] * 1001, "atlas": [(0.08, 0.06)] * 1001}
    missed = dict(truth, start=3.0, end=4.0, t=[3.0 + 0.001 * k for k in range(1001)])
    good = {"id": 1, "missed": 0, "link": "torso", "position": list(np.array(sp.position) + [0, 0.001, 0]),
            "force": 2.1, "valid": True}
    ghost = dict(good, id=2, position=[0.5, 0.5, 0.5])
    frames = [(1.5, [good]), (1.6, [good, ghost])]
    s = score(skin, [truth, missed], frames)
    assert s.truths == 2 and s.detected == 1 and s.false_ids == {2}
    assert s.position == pytest.approx([0.001, 0.001]) and s.force == pytest.approx([0.05, 0.05])


def test_the_scorer_tells_resolved_axes_from_unresolved_and_counts_confident_untruths() -> None:
    skin = _arm()
    (sp,) = skin.locate([0.08], [0.06])  # on the seam of the torso's two patches: straddled
    truth = {"finger": 0, "link": "torso", "kind": "single", "area": 3e-4, "pad": 0.02, "start": 1.0, "end": 2.0,
             "t": [1.0 + 0.001 * k for k in range(1001)], "point": [sp.position] * 1001,
             "normal": [sp.normal] * 1001, "force": [2.0] * 1001, "atlas": [(0.08, 0.06)] * 1001}
    off = np.array(sp.tangent_x) * 0.004 + np.array(sp.tangent_y) * 0.004  # 4 mm along both axes
    base = {"id": 1, "missed": 0, "link": "torso", "position": list(np.array(sp.position) + off), "force": 2.0,
            "valid": True}

    def scored(observable: list[bool], sigma: float):
        c = dict(base, observable=observable, cov=[[sigma * sigma, 0.0], [0.0, sigma * sigma]])
        return score(skin, [truth], [(1.5, [c])])

    precise = scored([True, True], 1e-4)  # 4 mm off, σ 0.1 mm: a confident untruth on each straddled axis
    n = len(precise.resolved)
    assert n >= 1 and precise.untrue == n and precise.unresolved == []
    assert precise.resolved == pytest.approx([0.004] * n)
    covered = scored([True, True], 3e-3)  # the same error inside 3 σ: no untruth
    assert covered.untrue == 0 and len(covered.resolved) == n
    unseen = scored([False, False], 3e-3)  # said unobservable: apart, and covered
    assert unseen.resolved == [] and unseen.untrue == 0 and len(unseen.unresolved) == n
    assert all(e <= 2 * sg for e, sg in unseen.unresolved)
    assert "resolved axes off by > 1 mm and > 3 sigma" in precise.table()


def test_link_frames_come_from_the_urdf(tmp_path) -> None:
    pytest.importorskip("yourdfpy")
    from cellbridge.daemon.shell.skin_file import load_skin

    (tmp_path / "arm.urdf").write_text("""<robot name="arm">
  <link name="base"/><link name="fore"/>
  <joint name="elbow" type="revolute">
    <parent link="base"/><child link="fore"/>
    <origin xyz="0 0 0.3" rpy="0 1.5707963267948966 0"/>
    <axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
</robot>""")
    skin_text = """urdf = "arm.urdf"
[[patch]]
name = "p"
link = "fore"
shape = "cylinder"
radius = 0.045
wrap = true
rows = 1
cols = 7
[[gateway]]
name = "g"
patch = "p"
"""
    (tmp_path / "skin.toml").write_text(skin_text)
    skin = load_skin(tmp_path / "skin.toml")
    fore = skin.link("fore")
    assert fore.parent == "base" and fore.declared
    assert np.allclose(skin.link_pose("fore")[:3, 3], [0, 0, 0.3])
    assert np.allclose(skin.link_pose("fore")[:3, 2], [1, 0, 0], atol=1e-9)  # z turned onto x
    (tmp_path / "skin.toml").write_text(skin_text.replace('link = "fore"', 'link = "hand"'))
    with pytest.raises(ValueError, match="no link 'hand'"):
        load_skin(tmp_path / "skin.toml")
    # without the URDF read (the emulator's way), its links are taken as named, undeclared
    assert not parse_skin(skin_text).link("fore").declared and math.isfinite(skin.side)


def test_a_footprint_across_a_seam_with_a_gap_is_straddled() -> None:
    from cellbridge.robot_score import _straddled

    skin = _arm()
    # The upper arm's columns are 41.9 mm apart, 40 mm wide: a 1.9 mm gap between them.
    # A 20 mm pad 4 mm inside a column reaches 4.1 mm onto the next one across the gap.
    left_edge = 0.24 + 0.5 * (2 * math.pi * 0.04 / 6 - skin.side) + 2 * math.pi * 0.04 / 6
    assert _straddled(skin, left_edge + 0.004, 0.02, 0.010) == (True, False)  # was (False, False)
    assert _straddled(skin, left_edge + 0.0105, 0.02, 0.010) == (False, False)  # 0.6 mm into the gap: on no element
    # the wrap seam (the band's two ends): the same
    assert _straddled(skin, 0.24 + 0.5 * (2 * math.pi * 0.04 / 6 - skin.side) + 0.004, 0.02, 0.010) == (True, False)
    # the torso's two patches meet without a gap: as before
    assert _straddled(skin, 0.08 + 0.004, 0.06, 0.010) == (True, False)


def _torso_truth(start: float, kind: str = "single") -> dict:
    skin = _arm()
    (sp,) = skin.locate([0.08], [0.06])
    n = 501
    return {"finger": 0, "link": "torso", "kind": kind, "area": 3e-4, "pad": 0.02, "start": start, "end": start + 0.5,
            "t": [start + 0.001 * k for k in range(n)], "point": [sp.position] * n, "normal": [sp.normal] * n,
            "force": [2.0] * n, "atlas": [(0.08, 0.06)] * n}


def test_one_id_matched_to_two_true_contacts_is_shown_not_counted_as_two_clean_detections() -> None:
    """Two presses one after the other at one place, published as one id: both are
    detected (a contact matched each), and the table says one id stood for two."""
    skin = _arm()
    a, b = _torso_truth(1.0), _torso_truth(2.0)
    c = {"id": 5, "missed": 0, "link": "torso", "position": list(a["point"][0]), "force": 2.0, "valid": True}
    s = score(skin, [a, b], [(1.2, [c]), (2.2, [c])])
    assert s.detected == 2 and s.ids_per_truth == [1, 1]
    assert s.truths_per_id == {5: 2}, s.truths_per_id
    rows = {r[0]: r[1] for r in s.rows()}
    assert rows["true contacts per id, max"] == "2", s.table()


def test_stray_true_contacts_are_counted_not_dropped() -> None:
    """A finger touching where the scenario did not script it (kind "stray") is not scored,
    and a contact on it is no false one: both said in the table."""
    skin = _arm()
    stray = _torso_truth(1.0, kind="stray")
    c = {"id": 5, "missed": 0, "link": "torso", "position": list(stray["point"][0]), "force": 2.0, "valid": True}
    s = score(skin, [stray, _torso_truth(3.0)], [(1.2, [c])])
    assert s.truths == 1 and s.not_scored == 1
    assert not s.false_ids, s.table()  # it touched something: not a false contact
    rows = {r[0]: r[1] for r in s.rows()}
    assert rows["true contacts not scored (stray touches)"] == "1", s.table()
    assert rows["  published ids on them"] == "1", s.table()


def test_reports_of_a_detected_id_before_its_press_or_after_its_release_are_counted() -> None:
    """A contact that matched its press but is still published 2 s after the release (or
    0.5 s before the press) is no false id: those reports are counted apart, target 0."""
    skin = _arm()
    a = _torso_truth(1.0)
    c = {"id": 5, "missed": 0, "link": "torso", "position": list(a["point"][0]), "force": 2.0, "valid": True}
    s = score(skin, [a], [(0.5, [c]), (1.2, [c]), (3.5, [c]), (3.6, [c])])
    assert s.detected == 1 and not s.false_ids
    assert s.off_truth == 3, s.table()
    rows = {r[0]: r[1] for r in s.rows()}
    assert rows["reports of detected ids while they matched nothing"] == "3", s.table()


def test_an_axis_inside_one_element_said_observable_and_far_off_is_a_confident_untruth() -> None:
    """A small press at an element's middle straddles no axis: its reports' position errors
    were scored nowhere, so a report 4 mm off with σ 0.1 mm (observable) passed as
    nothing; it is now counted, and an honest one (σ covering it) is not."""
    from cellbridge.robot_score import _straddled

    skin = _arm()
    ax, ay = (float(v) for v in skin.atlas[0])  # element 0's middle
    assert _straddled(skin, ax, ay, 0.005) == (False, False)
    (sp,) = skin.locate([ax], [ay])
    n = 501
    truth = {"finger": 0, "link": _link_of(skin, ax, ay), "kind": "single",
             "area": 8e-5, "pad": 0.01, "start": 1.0, "end": 1.5, "t": [1.0 + 0.001 * k for k in range(n)],
             "point": [sp.position] * n, "normal": [sp.normal] * n, "force": [2.0] * n, "atlas": [(ax, ay)] * n}
    off = np.array(sp.position) + 0.004 * np.array(sp.tangent_x)

    def scored(observable: list[bool], sigma: float):
        c = {"id": 1, "missed": 0, "link": truth["link"], "position": list(off), "force": 2.0, "valid": True,
             "observable": observable, "cov": [[sigma * sigma, 0.0], [0.0, sigma * sigma]]}
        return score(skin, [truth], [(1.2, [c])])

    lying = scored([True, True], 1e-4)
    assert lying.inside_untrue == 1 and len(lying.inside) == 2, lying.table()
    rows = {r[0]: r[1] for r in lying.rows()}
    assert rows["  said observable, off by > 1 mm and > 3 sigma"] == "1", lying.table()
    honest = scored([False, False], 0.012)
    assert honest.inside_untrue == 0 and all(e <= 2 * sg for e, sg in honest.inside), honest.table()


def _link_of(skin, ax: float, ay: float) -> str:
    return skin.charts[int(skin.chart_at([ax], [ay])[0])].link

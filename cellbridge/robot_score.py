"""Scoring the daemon's contacts against the simulated robot's ground truth.

Inputs are plain records, so a run in virtual time and a recording of a real-time run
(``cellbridge sub contact``) score alike: the ground truth of every contact (link, and per
simulation step its point, force and atlas place: :class:`~cellbridge.emulator.world.robot_world.Truth`
as a dict) and the ``contact`` messages the daemon published (each frame's ``t_sample``
on the truth's clock, its contacts with ``link``, ``position``, ``force``,
``observable``).

A published contact *matches* a true contact active at the frame's instant on the same
link within ``MATCH`` of its point. Per true contact: *detected* when some contact
matched it; while it is held (from its ramp's end to the release's start), each matching
contact's position error and force error. The position error counts the axes of the skin
the true footprint straddles (crosses into a neighbour element): the readings of a
footprint inside one element cannot place it along that axis, which the daemon says
(``observable``) and reports the range's middle; such an axis is scored apart, for
honesty only (its σ should cover the error; one said observable and off by more than
1 mm and 3 σ is a confident untruth). *False* contacts: published contact ids
that never matched a true contact (nor a stray touch: a finger the scenario did not script,
counted apart as not scored). One id matched to two true contacts detects both, and the
table's "true contacts per id" says so; the reports of a matched id made while it matched
nothing (it lingers past the release, or came before the press) are counted apart.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cellbridge.tactile.skin_geometry import SkinGeometry

__all__ = ["MATCH", "Score", "idle_false_ids", "idle_line", "score"]

MATCH = 0.020  #: m: farthest a published contact may be from a true one and match it
SETTLE = 0.05  #: s after a press's ramp before its readings are held steady enough to score


@dataclass
class Score:
    truths: int = 0
    detected: int = 0
    by_kind: dict[str, list[int]] = field(default_factory=dict)  # kind -> [truths, detected]
    position: list[float] = field(default_factory=list)  # m, along the straddled axes, per matched report
    position_3d: list[float] = field(default_factory=list)  # m, reports of footprints straddling both axes
    #: m, per straddled axis the report calls observable (its readings resolve it)
    resolved: list[float] = field(default_factory=list)
    #: (error, σ) in m, per straddled axis the report calls unobservable (the neighbour's share
    #: under its touch threshold): honest when σ covers the error
    unresolved: list[tuple[float, float]] = field(default_factory=list)
    untrue: int = 0  #: resolved axes off by more than 1 mm and 3 σ: confident untruths
    #: (error, σ) in m, per axis the footprint does not straddle (inside one element along it:
    #: the readings cannot place it, the report should say the element's middle and a σ
    #: that covers it); and of them those said observable, off by > 1 mm and > 3 σ
    inside: list[tuple[float, float]] = field(default_factory=list)
    inside_untrue: int = 0
    force: list[float] = field(default_factory=list)  # relative error per matched report
    false_ids: set[int] = field(default_factory=set)
    reports: int = 0
    ids_per_truth: list[int] = field(default_factory=list)
    #: published id -> true contacts it matched: more than one is one id standing for two
    #: presses (each still detected), which the table shows
    truths_per_id: dict[int, int] = field(default_factory=dict)
    #: true contacts not scored: stray touches (a finger where the scenario scripted none)
    #: and truths with no step; published ids on a stray are no false contacts
    not_scored: int = 0
    stray_ids: set[int] = field(default_factory=set)
    #: reports of ids that matched a true contact, made while they matched none (before its
    #: press, after its release, or wandered off): a detected contact that lingers is no false
    #: id, and would otherwise count nowhere
    off_truth: int = 0

    def rows(self) -> list[tuple[str, str, str]]:
        """(what, measured, target) rows of the accuracy table."""
        pct = lambda a, q: float(np.percentile(a, q)) if len(a) else math.nan
        det = 100.0 * self.detected / self.truths if self.truths else math.nan
        rows = [("contacts (true)", f"{self.truths}", ">= 200 in the bench"),
                ("detected", f"{det:.1f} %", ">= 99 %")]
        for kind, (n, d) in sorted(self.by_kind.items()):
            rows.append((f"  detected, {kind}", f"{d}/{n}", ""))
        rows += [
            ("position error, straddled axes, median", f"{1e3 * pct(self.position, 50):.2f} mm", "<= 2 mm"),
            ("position error, straddled axes, p95", f"{1e3 * pct(self.position, 95):.2f} mm", "<= 5 mm"),
            ("position error 3-D, both axes straddled, median", f"{1e3 * pct(self.position_3d, 50):.2f} mm", ""),
            ("  per straddled axis the readings resolve, median", f"{1e3 * pct(self.resolved, 50):.2f} mm", ""),
            ("  per straddled axis the readings resolve, p95", f"{1e3 * pct(self.resolved, 95):.2f} mm", ""),
            ("  resolved axes off by > 1 mm and > 3 sigma", f"{self.untrue} of {len(self.resolved)}", "0"),
            ("  straddled axes not resolved (said unobservable)", f"{len(self.unresolved)}", ""),
            ("  ... of them within 2 sigma",
             f"{sum(1 for e, sg in self.unresolved if e <= 2 * sg)}", "all"),
            ("axes inside one element (not straddled)", f"{len(self.inside)}", ""),
            ("  ... of them within 2 sigma", f"{sum(1 for e, sg in self.inside if e <= 2 * sg)}", "all"),
            ("  said observable, off by > 1 mm and > 3 sigma", f"{self.inside_untrue}", "0"),
            ("force error, median", f"{100 * pct(self.force, 50):.2f} %", "<= 3 %"),
            ("force error, p95", f"{100 * pct(self.force, 95):.2f} %", ""),
            ("ids per detected contact, max", f"{max(self.ids_per_truth, default=0)}", "1"),
            ("true contacts per id, max", f"{max(self.truths_per_id.values(), default=0)}", "1"),
            ("false contacts (ids matching nothing)", f"{len(self.false_ids)}", "0"),
            ("reports of detected ids while they matched nothing", f"{self.off_truth}", "0"),
            ("true contacts not scored (stray touches)", f"{self.not_scored}", ""),
            ("  published ids on them", f"{len(self.stray_ids)}", ""),
            ("reports scored", f"{self.reports}", ""),
        ]
        return rows

    def table(self) -> str:
        rows = [("", "measured", "target")] + self.rows()
        w = [max(len(r[i]) for r in rows) for i in range(3)]
        return "\n".join(f"{r[0]:<{w[0]}}  {r[1]:>{w[1]}}  {r[2]}" for r in rows)


def _straddled(skin: SkinGeometry, ax: float, ay: float, r: float) -> tuple[bool, bool]:
    """Whether a footprint of radius ``r`` at atlas (ax, ay) reaches into a neighbour
    element along the atlas x and y (half a millimetre onto another element, at least,
    beyond the gap between them where the elements' pitch exceeds their side)."""
    lay = skin.layout()
    i = int(lay.element_at([[ax, ay]])[0])
    if i < 0:
        return True, True  # in a seam: between elements on its axis at least
    out = []
    for axis in (0, 1):
        hit = False
        for sgn in (-1.0, 1.0):
            probe = [ax, ay]
            probe[axis] += sgn * (r - 0.5e-3)  # the footprint's reach, less half a millimetre
            px = skin.wrap_x(probe[0], probe[1])
            j = int(lay.element_at([[px, probe[1]]])[0])
            hit |= j >= 0 and j != i
        out.append(hit)
    return out[0], out[1]


def _per_axis(s: Score, c: dict[str, Any], straddled: tuple[bool, bool], errors: list[float]) -> None:
    """Each straddled axis's error, apart by whether the report calls the axis observable."""
    obs = c.get("observable") or (False, False)
    cov = c.get("cov")
    for axis in (0, 1):
        if not straddled[axis]:
            continue
        err = abs(errors[axis])
        sigma = math.sqrt(float(cov[axis][axis])) if cov else math.nan
        if obs[axis]:
            s.resolved.append(err)
            s.untrue += int(err > 1e-3 and not err <= 3 * sigma)
        else:
            s.unresolved.append((err, sigma))


def _inside(s: Score, c: dict[str, Any], straddled: tuple[bool, bool], errors: list[float]) -> None:
    """Each axis the footprint does not straddle: its error and σ, and whether the report
    calls it observable while off by more than 1 mm and 3 σ (a confident untruth)."""
    obs = c.get("observable") or (False, False)
    cov = c.get("cov")
    for axis in (0, 1):
        if straddled[axis]:
            continue
        err = abs(errors[axis])
        sigma = math.sqrt(float(cov[axis][axis])) if cov else math.nan
        s.inside.append((err, sigma))
        s.inside_untrue += int(bool(obs[axis]) and err > 1e-3 and not err <= 3 * sigma)


def score(skin: SkinGeometry, truths: Iterable[dict[str, Any]], frames: Iterable[tuple[float, list[dict[str, Any]]]],
          ramp: float = 0.05) -> Score:
    """Score ``frames`` (``(t, contacts)``: each published frame's instant on the truth's
    clock and its contacts) against ``truths`` (:meth:`Truth.to_dict` records)."""
    everything = list(truths)
    tr = [t for t in everything if t["kind"] != "stray" and len(t["t"]) > 0]
    strays = [t for t in everything if t["kind"] == "stray" and len(t["t"]) > 0]
    s = Score(truths=len(tr), not_scored=len(everything) - len(tr))
    t_arr = [np.asarray(t["t"]) for t in tr]
    matched_ids: dict[int, set[int]] = {k: set() for k in range(len(tr))}
    any_match: dict[int, bool] = {}
    straddle_memo: dict[tuple[int, int], tuple[bool, bool]] = {}
    truths_of_id: dict[int, set[int]] = {}
    unmatched: dict[int, int] = {}  # id -> its reports that matched no true contact
    for t, contacts in frames:
        for c in contacts:
            if c.get("missed", 0) != 0:
                continue
            cid = int(c["id"])
            any_match.setdefault(cid, False)
            best, best_d, best_j = None, math.inf, -1
            for k, truth in enumerate(tr):
                if not (truth["start"] - 0.02 <= t <= truth["end"] + 0.02) or truth["link"] != c.get("link"):
                    continue
                j = int(np.clip(np.searchsorted(t_arr[k], t), 0, len(t_arr[k]) - 1))
                d = float(np.linalg.norm(np.asarray(c["position"]) - np.asarray(truth["point"][j])))
                if d < best_d:
                    best, best_d, best_j = k, d, j
            if best is None or best_d > MATCH:
                if _near(strays, t, c):
                    any_match[cid] = True  # a real touch, unscripted: no false contact
                    s.stray_ids.add(cid)
                else:
                    unmatched[cid] = unmatched.get(cid, 0) + 1
                continue
            any_match[cid] = True
            matched_ids[best].add(cid)
            truths_of_id.setdefault(cid, set()).add(best)
            truth = tr[best]
            held = truth["start"] + ramp + SETTLE <= t <= truth["end"] - ramp
            if not held:
                continue
            s.reports += 1
            ft = float(truth["force"][best_j])
            if c.get("valid") and isinstance(c.get("force"), (int, float)) and math.isfinite(c["force"]) and ft > 0:
                s.force.append(abs(float(c["force"]) - ft) / ft)
            ax, ay = truth["atlas"][best_j]
            key = (best, best_j // 20)  # the footprint moves little in 20 ms
            if key not in straddle_memo:
                straddle_memo[key] = _straddled(skin, ax, ay, 0.5 * truth["pad"])
            sx, sy = straddle_memo[key]
            (sp,) = skin.locate([ax], [ay])
            e = np.asarray(c["position"]) - np.asarray(truth["point"][best_j])
            _inside(s, c, (sx, sy), [float(e @ np.asarray(sp.tangent_x)), float(e @ np.asarray(sp.tangent_y))])
            if not (sx or sy):
                continue
            parts = [float(e @ np.asarray(sp.tangent_x)) if sx else 0.0, float(e @ np.asarray(sp.tangent_y)) if sy else 0.0]
            s.position.append(math.hypot(*parts))
            _per_axis(s, c, (sx, sy), parts)
            if sx and sy:
                s.position_3d.append(float(np.linalg.norm(e)))
    for k, truth in enumerate(tr):
        n_d = s.by_kind.setdefault(truth["kind"], [0, 0])
        n_d[0] += 1
        if matched_ids[k]:
            s.detected += 1
            n_d[1] += 1
            s.ids_per_truth.append(len(matched_ids[k]))
    s.false_ids = {cid for cid, ok in any_match.items() if not ok}
    s.off_truth = sum(n for cid, n in unmatched.items() if any_match[cid])
    s.truths_per_id = {cid: len(ks) for cid, ks in truths_of_id.items()}
    return s


def _near(truths: list[dict[str, Any]], t: float, c: dict[str, Any]) -> bool:
    """Whether contact ``c`` at ``t`` lies within :data:`MATCH` of one of ``truths`` active then on its link."""
    for truth in truths:
        if not (truth["start"] - 0.02 <= t <= truth["end"] + 0.02) or truth["link"] != c.get("link"):
            continue
        j = int(np.clip(np.searchsorted(np.asarray(truth["t"]), t), 0, len(truth["t"]) - 1))
        if float(np.linalg.norm(np.asarray(c["position"]) - np.asarray(truth["point"][j]))) <= MATCH:
            return True
    return False


def idle_false_ids(frames: Iterable[tuple[float, list[dict[str, Any]]]], busy: float) -> set[int]:
    """The ids published (with their elements seen: ``missed`` 0) after ``busy``, the
    instant the scenario's last press is over: nothing touches the skin then, so each is
    a false contact."""
    return {int(c["id"]) for t, cs in frames if t > busy for c in cs if c.get("missed", 0) == 0}


def idle_line(ids: int, seconds: float) -> str:
    """The idle false contacts as the target reads them: a rate over the idle time, not a
    bare count (one in 30 s is twenty per 10 minutes)."""
    rate = 600.0 * ids / seconds if seconds > 0 else math.nan
    return f"idle {seconds:.0f} s: {ids} false contacts ({rate:.1f} per 10 minutes; target at most 1)"

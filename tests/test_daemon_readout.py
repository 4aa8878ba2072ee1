"""The pipeline reading skin frames from READOUT records (synthesized gateway bytes): a frame
complete by its records or its deadline, each element a new reading, its previous one
(its bridge said unchanged) or unknown, and contacts that say what they do not know."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.protocol import Hello

from daemon_traffic import CLOCK, GridFrames
from support.pipeline_helpers import published, worker

T0 = 1_700_000_000.0
SPAN = 0.004  # s: the records' readout span
SEAM = (0.020, 0.006, 3.0, 0.012)  # across the seam of bridges 1 and 2 (x 20 mm)
CORNER = (0.0585, 0.0625, 3.0, 0.020)  # across the corner of bridges 6, 7, 10 and 11 of a 4x4 skin


def make(extra: dict | None = None) -> Pipeline:
    cfg = parse_config({"link": [{"name": "gw", "url": "/dev/null"}, {"name": "gw2", "url": "/dev/null"}],
                        "calibration": {"n_baseline": 10}, **(extra or {})})
    return Pipeline(cfg)


def arrive(sk: GridFrames, k: int) -> float:
    """When a gateway's record of frame k reaches the host: its readout's end, plus a little."""
    return T0 + k / sk.rate + SPAN + 0.0005


def start(p: Pipeline, sk: GridFrames, frames: int = 20) -> int:
    """HELLOs, then ``frames`` quiet frames (the baselines); the next frame's index."""
    p.feed("gw", sk.hellos() + sk.beacons(), T0)
    for k in range(frames):
        p.feed("gw", sk.readout(k), arrive(sk, k))
    return frames


def contact_of(p: Pipeline, runs: int = 1) -> dict:
    """The ``contact`` message of the pipeline's next job, estimated ``runs`` times in a row
    on one worker (each after the same frame's job: the tracker sees one frame per run)."""
    w = worker()
    job = p.contact_job()
    assert job is not None
    msg = None
    for _ in range(runs):
        msg = p.contact_frame(job, w.estimate_now(job)).payload
    assert msg is not None
    return msg


def test_a_press_read_by_frames_is_one_contact_and_its_samples_carry_the_frames_cycle() -> None:
    sk = GridFrames(rows=4, cols=4)
    p = make()
    k = start(p, sk)
    p.want({"element", "contact", "raw"})
    w = worker()
    reports = []
    for i in range(k, k + 10):
        out = p.feed("gw", sk.readout(i, CORNER), arrive(sk, i))
        (raw,) = [m for t, m in published(out) if t == "raw"]
        assert raw["link"] == "gw" and raw["bridge"] == sk.ids and raw["cycle"] == [i * CLOCK // int(sk.rate)] * 16
        job = p.contact_job()
        # (the host's map puts a frame at the least delay its records came with after the gates opened)
        assert job is not None and job.snapshot.t_frame == pytest.approx(arrive(sk, i), abs=1e-6)
        reports += p.contact_frame(job, w.estimate_now(job)).payload["contacts"]
        (el,) = [m for t, m in published(out) if t == "element"]
        assert el["cycle"] == [i * CLOCK // int(sk.rate)] * 16  # the frame's global cycle, every sample
        assert el["index"] == [i] * 16 and len(set(el["t_sample"])) == 1 and all(el["on_time"])
    assert {c["id"] for c in reports} == {0}
    for c in reports:
        assert sorted(c["elements"]) == [6, 7, 10, 11] and c["unknown_near"] == []
        assert c["force"] == pytest.approx(3.0, rel=0.05)
        assert math.hypot(c["x"] - CORNER[0], c["y"] - CORNER[1]) <= 1e-3
    health = p.health_body(arrive(sk, k + 10))
    assert health["frames"]["frames_complete"] == k + 10 and health["frames"]["unknown_element_frames"] == 0
    assert not health["silent"]


def test_an_element_missing_from_the_frame_is_unknown_and_the_contact_says_so_without_a_confident_centre() -> None:
    """A seam press whose one side is missing: the contact lists it, and its position and force
    σ cover the truth. (The fit of the known side alone put it at that element's centre with
    about half the force, σ a fraction of a millimetre: a confident wrong contact.)"""
    sk = GridFrames()
    p = make()
    k = start(p, sk)
    for i in range(k, k + 3):
        p.feed("gw", sk.readout(i, SEAM, missing=(2,)), arrive(sk, i))
    msg = contact_of(p)
    assert msg["unknown"] == [2]
    (c,) = msg["contacts"]
    assert c["unknown_near"] == [2] and c["elements"] == [1]
    assert abs(c["x"] - SEAM[0]) <= c["sigma_x"] and abs(c["y"] - SEAM[1]) <= c["sigma_y"]
    assert abs(c["force"] - SEAM[2]) <= c["sigma_force"]
    assert not c["observable"][0]  # the unknown side widens x: its middle, not a fit of half a press
    lo, hi = sk.layout.bounds[0, 0], sk.layout.bounds[1, 2]
    assert c["x"] == pytest.approx(0.5 * (lo + hi)) and c["sigma_x"] == pytest.approx(0.5 * (hi - lo))


def test_an_unchanged_element_keeps_its_reading_because_its_bridge_said_so() -> None:
    """Event-based: the press's first frame has its samples, every frame after says unchanged:
    the contact holds its force and place, with nothing unknown."""
    sk = GridFrames(rows=4, cols=4)
    p = make()
    k = start(p, sk)
    p.feed("gw", sk.readout(k, CORNER), arrive(sk, k))
    w = worker()
    for i in range(k + 1, k + 8):
        p.feed("gw", sk.readout(i, CORNER, unchanged=tuple(sk.ids)), arrive(sk, i))
        job = p.contact_job()
        assert job is not None and job.snapshot.unknown is not None and not job.snapshot.unknown.any()
        msg = p.contact_frame(job, w.estimate_now(job)).payload
        (c,) = msg["contacts"]
        assert c["id"] == 0 and sorted(c["elements"]) == [6, 7, 10, 11] and c["unknown_near"] == []
        assert c["force"] == pytest.approx(3.0, rel=0.05)
        assert math.hypot(c["x"] - CORNER[0], c["y"] - CORNER[1]) <= 1e-3
        assert c["cycles"] == [k * CLOCK // int(sk.rate)] * 4  # the reading is the sample of frame k


def test_unchanged_after_a_missing_frame_is_unknown_until_the_next_sample() -> None:
    """Once an element was missing, a sample of it may have been lost: "unchanged" then
    refers to a reading the host never got, and the element is unknown until it sends one."""
    sk = GridFrames()
    p = make()
    k = start(p, sk)
    p.feed("gw", sk.readout(k, SEAM, missing=(2,)), arrive(sk, k))  # bridge 2's sample of the press lost
    p.feed("gw", sk.readout(k + 1, SEAM, unchanged=(1, 2, 3, 4)), arrive(sk, k + 1))
    job = p.contact_job()
    assert job is not None and job.snapshot.unknown is not None and job.snapshot.unknown.tolist() == [False, True, False, False]
    p.feed("gw", sk.readout(k + 2, SEAM, unchanged=(1, 3, 4)), arrive(sk, k + 2))  # its next sample
    p.feed("gw", sk.readout(k + 3, SEAM, unchanged=(1, 2, 3, 4)), arrive(sk, k + 3))
    job = p.contact_job()
    assert job is not None and job.snapshot.unknown is not None and not job.snapshot.unknown.any()
    assert sorted(job.snapshot.ids[job.snapshot.touched].tolist()) == [1, 2]


def two_gateway_skin() -> tuple[GridFrames, Pipeline, int]:
    """A 2x2 skin: gateway 1 (link gw) reads bridges 1 and 2, gateway 4 (link gw2) 3 and 4."""
    sk = GridFrames()
    p = make()
    p.feed("gw", sk.hellos(), T0)
    k = 0
    for k in range(20):
        p.feed("gw", sk.readout(k, gateway=1, bridges=[1, 2]), arrive(sk, k))
        p.feed("gw2", sk.readout(k, gateway=4, bridges=[3, 4]), arrive(sk, k) + 0.001)
    return sk, p, k + 1


def test_a_frame_waits_for_the_second_gateway_until_its_deadline_then_its_elements_are_unknown() -> None:
    sk, p, k = two_gateway_skin()
    p.contact_job()
    margin = p.config.frames.margin
    before = p.health_body(arrive(sk, k))["frames"]
    assert before["late_records"] == 1  # gateway 4's first record: frame 0 went out on gateway 1's alone
    p.feed("gw", sk.readout(k, SEAM, gateway=1, bridges=[1, 2]), arrive(sk, k))
    assert p.contact_job() is None  # gateway 4's record of k may still come
    due = p.contact_due(arrive(sk, k))
    t_frame = arrive(sk, k)  # (the map's: the least delay of the records after their gates opened)
    # (+ a part's serial time at most: 258 bytes at 1 Mbit/s)
    assert t_frame + SPAN + margin <= due <= t_frame + SPAN + margin + 0.00258 + 1e-6
    assert p.contact_job(due - 1e-4) is None
    job = p.contact_job(due)
    assert job is not None and job.snapshot.unknown is not None and job.snapshot.unknown.tolist() == [False, False, True, True]
    late = p.feed("gw2", sk.readout(k, SEAM, gateway=4, bridges=[3, 4]), due + 0.01)
    # (the frame's element messages, of bridges 1 and 2, come with the next read) a late record rewrites nothing
    assert [m["bridge"] for t, m in published(late) if t == "element"] == [[1, 2]]
    frames = p.health_body(due + 0.01)["frames"]
    assert frames["late_records"] == 2 and frames["frames_by_deadline"] == 1
    assert frames["unknown_element_frames"] == before["unknown_element_frames"] + 2


def test_a_frame_whose_records_all_came_is_estimated_at_once_not_at_its_deadline() -> None:
    sk, p, k = two_gateway_skin()
    p.contact_job()
    p.feed("gw", sk.readout(k, SEAM, gateway=1, bridges=[1, 2]), arrive(sk, k))
    now = arrive(sk, k) + 0.001
    p.feed("gw2", sk.readout(k, SEAM, gateway=4, bridges=[3, 4]), now)
    assert p.contact_due(now) == now
    job = p.contact_job(now)
    assert job is not None and job.snapshot.unknown is not None and not job.snapshot.unknown.any()
    assert sorted(job.snapshot.ids[job.snapshot.touched].tolist()) == [1, 2]


def test_records_read_one_byte_at_a_time_give_the_same_frames() -> None:
    sk = GridFrames()
    whole, bytewise = make(), make()
    quiet = [(arrive(sk, i), sk.readout(i)) for i in range(20)]  # (the skin's counts jitter: made once)
    for p in (whole, bytewise):
        p.want({"element", "contact"})
        p.feed("gw", sk.hellos(), T0)
        for t, data in quiet:
            p.feed("gw", data, t)
    k = 20
    out_whole: list = []
    out_bytes: list = []
    for i in range(k, k + 4):
        data = sk.readout(i, SEAM, unchanged=(3, 4)) if i % 2 else sk.readout(i, SEAM, missing=(4,))
        out_whole += published(whole.feed("gw", data, arrive(sk, i)))
        for j in range(len(data)):
            out_bytes += published(bytewise.feed("gw", data[j:j + 1], arrive(sk, i)))
    def packed(out: list) -> list[bytes]:  # (NaN == NaN as bytes)
        return [msgpack.packb((t, {key: v for key, v in m.items() if key != "seq"})) for t, m in out]

    assert out_whole and packed(out_whole) == packed(out_bytes)
    a, b = whole.contact_job(), bytewise.contact_job()
    assert a is not None and b is not None
    np.testing.assert_array_equal(a.snapshot.unknown, b.snapshot.unknown)
    np.testing.assert_array_equal(a.snapshot.dc, b.snapshot.dc)


def test_a_bridge_on_no_schedule_is_read_by_the_fallback_rule() -> None:
    """Bridge 4 boots without mesh time and sends DATA; the others are on the schedule. In a
    frame, its newest DATA reading within one sample period counts; older, it is unknown."""
    sk = GridFrames()
    p = make()
    p.feed("gw", sk.hellos(), T0)
    data_only = sk.slot(0).split(b"\x00\x00")[3]  # (bridge 4's DATA frame of one slot, framed below)
    assert data_only
    k = 0
    for k in range(30):
        p.feed("gw", sk.readout(k, bridges=[1, 2, 3]), arrive(sk, k))
        p.feed("gw", b"\x00" + sk.slot(k).split(b"\x00\x00")[3], arrive(sk, k))
    job = p.contact_job()
    assert job is not None and job.snapshot.unknown is not None and not job.snapshot.unknown.any()
    for i in range(k + 1, k + 5):  # bridge 4 goes quiet: its reading grows older than a period
        p.feed("gw", sk.readout(i, bridges=[1, 2, 3]), arrive(sk, i))
    job = p.contact_job()
    assert job is not None and job.snapshot.unknown is not None and job.snapshot.unknown.tolist() == [False, False, False, True]


def test_bridges_on_the_schedule_are_alive_though_they_send_no_frame_of_their_own() -> None:
    sk = GridFrames()
    p = make()
    k = start(p, sk)
    for i in range(k, k + 300):  # 3 s of frames: past bridge_timeout
        p.feed("gw", sk.readout(i, unchanged=(2, 3), missing=(4,)), arrive(sk, i))
    p.tick(arrive(sk, k + 300), force=True)
    body = p.health_body(arrive(sk, k + 300))
    assert body["silent"] == [4]  # said missing for 3 s: no word of it came


def test_samples_of_a_bridge_known_only_by_its_records_are_counted_unplaced() -> None:
    # A starved skin: one bridge's HELLO came, the others' not yet, and their samples come
    # in the gateway's readout records before anything else of theirs. The host cannot
    # place them; it counts them per bridge and reads on (this read once failed whole).
    sk = GridFrames(rows=2, cols=2)
    p = make()
    first = sk.ids[0]
    hello = Hello(first, "test-1", float(sk.layout.centres[0, 0]), float(sk.layout.centres[0, 1]),
                  float(sk.layout.side), CLOCK, 3)
    p.feed("gw", sk._frame(first, hello), T0)
    for k in range(5):
        p.feed("gw", sk.readout(k), arrive(sk, k))
    h = p.health_body(arrive(sk, 5))
    assert all(h["bridges"][str(b)]["unmapped_samples"] >= 4 for b in sk.ids[1:])
    assert h["bridges"][str(first)]["unmapped_samples"] == 0
    assert h["frames"]["frames_complete"] >= 4
    # their HELLOs come, and they are placed
    p.feed("gw", sk.hellos(), arrive(sk, 5))
    for k in range(5, 40):
        p.feed("gw", sk.readout(k), arrive(sk, k))
    assert p.health_body(arrive(sk, 40))["unplaced"] == []

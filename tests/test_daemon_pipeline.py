"""The daemon's sans-I/O pipeline on synthesized gateway traffic (no sockets, no asyncio)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.daemon.shell.layout_file import load_layout
from cellbridge.protocol import (
    ADDR_BROADCAST,
    Beacon,
    Command,
    Data,
    Frame,
    Mode,
    Op,
    Sample,
    StreamDecoder,
    encode_stream,
    fragment,
)
from cellbridge.tactile import adc_code, grid_layout, layout_to_toml

from daemon_traffic import CLOCK, GridFrames, staggered
from support.pipeline_helpers import estimate, logged, published, snapshot, worker

T0 = 1_700_000_000.0
STRADDLE = (0.020, 0.006, 3.0, 0.012)  # on the seam of bridges 1 and 2


def make(extra: dict | None = None, layout=None) -> Pipeline:
    cfg = parse_config({"link": [{"name": "gw", "url": "/dev/null"}, {"name": "gw2", "url": "/dev/null"}],
                        **(extra or {})})
    return Pipeline(cfg, layout)


def settle(p: Pipeline, sk: GridFrames, n: int = 60, link: str = "gw") -> float:
    p.feed(link, sk.hellos() + sk.beacons(), T0)
    for k, data in sk.stream(n):
        p.feed(link, data, T0 + k / sk.rate)
    return T0 + n / sk.rate


def press(p: Pipeline, sk: GridFrames, contact, start: int, n: int = 10) -> list:
    out = []
    for k, data in sk.stream(n, contact, start=start):
        out = p.feed("gw", data, T0 + k / sk.rate)
    return out


def topic(out: list, name: str) -> dict:
    return [m for t, m in published(out) if t == name][-1]


def test_press_gives_force_on_element_and_position_on_contact() -> None:
    sk = GridFrames()
    p = make()
    settle(p, sk)
    out = press(p, sk, STRADDLE, 60)
    el = topic(out, "element")
    assert el["v"] == 2 and "t_host" in el and len(el["cycle"]) == 4
    force = np.nansum(np.where(el["valid"], el["force"], 0.0))
    touched = [b for b, t in zip(el["bridge"], el["touched"]) if t]
    assert touched == [1, 2]
    job = p.contact_job()
    assert job is not None
    _, msg = estimate(p, job, runs=3)  # a contact is reported once it persisted three estimates
    (c,) = msg["contacts"]
    assert c["id"] == 0 and c["age"] == 3
    assert c["x"] == pytest.approx(STRADDLE[0], abs=1e-3)
    assert c["force"] == pytest.approx(3.0, rel=0.01)
    assert force == pytest.approx(3.0, rel=0.05)  # per element shares of the same press
    assert sorted(c["elements"]) == [1, 2] and len(c["cycles"]) == 2
    assert msg["v"] == 2 and msg["t_sample"] is not None


def test_sample_times_follow_the_bridge_clock() -> None:
    sk = GridFrames()
    p = make()
    settle(p, sk, 200)
    out = press(p, sk, None, 200, 5)
    el = topic(out, "element")
    k = 204
    assert el["t_bridge"][0] == pytest.approx((sk.cycle0 + k * CLOCK / sk.rate) / CLOCK)
    assert el["t_sample"][0] == pytest.approx(T0 + k / sk.rate, abs=1e-6)


def test_garbage_and_truncated_frames_are_counted_not_fatal() -> None:
    sk = GridFrames()
    p = make()
    t = settle(p, sk, 60)
    one = sk.slot(61).split(b"\x00")[1]  # the COBS bytes of one frame
    junk = b"\x00garbage\x01\x02\x00" + one[: len(one) // 2] + b"\x00" + bytes(range(1, 200)) + b"\x00"
    p.feed("gw", junk, t)
    out = p.feed("gw", sk.slot(62), t + 0.01)
    assert len(topic(out, "element")["bridge"]) == 4
    links = p.health_body(t)["links"]["gw"]
    assert links["framing_errors"] + links["crc_errors"] >= 3
    assert links["bytes"] > 0


def test_cross_link_duplicates_are_removed_and_loss_counted() -> None:
    sk = GridFrames()
    p = make()
    settle(p, sk, 60)
    slots = [sk.slot(k) for k in range(60, 70)]
    n_elem = 0
    for i, data in enumerate(slots):
        t = T0 + (60 + i) / 100
        for link in ("gw", "gw2"):  # both gateways hear everything
            for _, m in published(p.feed(link, data, t)):
                if "force" in m:
                    n_elem += len(m["bridge"])
    assert n_elem == 40
    assert p.health_body(T0 + 1)["links"]["gw2"]["duplicates"] == 40
    sk.slot(70)  # one slot lost on the way
    p.feed("gw", sk.slot(71), T0 + 0.71)
    bridges = p.health_body(T0 + 0.72)["bridges"]
    assert all(bridges[str(b)]["lost"] == 1 for b in sk.ids)


def test_fragmented_data_is_reassembled() -> None:
    sk = GridFrames()
    p = make()
    settle(p, sk, 60)
    samples = tuple(Sample(0, sk.cycle0 + 61 * 500_000 + i, 19600, 15800, 0) for i in range(30))
    big = Frame(src=1, dst=0, origin=1, seq=sk.seq[1], payload=Data(Mode.COUNTER, samples))
    frags = fragment(big, tag=9)
    assert len(frags) > 1
    out = p.feed("gw", b"".join(encode_stream(f) for f in frags), T0 + 0.61)
    assert len(topic(out, "element")["bridge"]) == 30


def test_commands_go_to_the_link_a_bridge_was_heard_on_and_complete_on_reply() -> None:
    sk = GridFrames()
    p = make()
    settle(p, sk, 5, link="gw2")
    pending, writes = p.command(int(Op.SET_GATE), 50_000, 3, T0, 1.0)
    assert [w.link for w in writes] == ["gw2"]
    (frame,) = StreamDecoder().feed(writes[0].data)
    assert frame.dst == 3 and frame.payload == Command(pending.token, Op.SET_GATE, 50_000)
    p.feed("gw2", sk.reply(3, pending.token, Op.SET_GATE), T0 + 0.01)
    (done,) = p.commands.done(T0 + 0.01)
    assert done.result()["replies"]["3"]["status"] == "OK" and done.result()["missing"] == []
    assert p.batches.gate[3] == 50_000.0
    bpending, bwrites = p.command(int(Op.SET_RATE), 50, None, T0, 1.0)
    assert sorted(w.link for w in bwrites) == ["gw", "gw2"]
    assert StreamDecoder().feed(bwrites[0].data)[0].dst == ADDR_BROADCAST
    p.feed("gw2", sk.reply(1, bpending.token, Op.SET_RATE), T0 + 0.02)
    assert p.commands.done(T0 + 0.5) == []
    (late,) = p.commands.done(T0 + 1.5)
    assert late.result()["missing"] == [2, 3, 4]
    with pytest.raises(ValueError, match="bridge 99"):
        p.command(int(Op.PING), None, 99, T0, 1.0)


def test_halved_gate_reads_the_same_capacitance() -> None:
    sk = GridFrames()
    p = make()
    settle(p, sk, 60)
    pending, _ = p.command(int(Op.SET_GATE), 50_000, 2, T0, 1.0)
    p.feed("gw", sk.reply(2, pending.token, Op.SET_GATE, 50_000), T0 + 0.6)
    k1, k2 = sk.counts_for(None, np.zeros((2, 4)))
    data = encode_stream(Frame(1, 0, 2, sk.seq[2], Data(Mode.COUNTER, (Sample(0, 10**9, int(k1[1]) // 2,
                                                                               int(k2[1]) // 2, 0),))))
    el = topic(p.feed("gw", data, T0 + 0.61), "element")
    assert el["c1"][0] == pytest.approx(sk.params.C1_rest, rel=2e-4)


def test_adc_mode_is_converted() -> None:
    sk = GridFrames()
    p = make()
    settle(p, sk, 60)
    rng = np.random.default_rng(0)
    over = 64
    codes = adc_code(np.full(over, sk.params.C1_rest), sk.chip, rng.normal(0, 0.5, over)).sum()
    codes2 = adc_code(np.full(over, sk.params.C2_rest), sk.chip, rng.normal(0, 0.5, over)).sum()
    data = encode_stream(Frame(1, 0, 3, sk.seq[3], Data(Mode.ADC, (Sample(0, 10**9, int(codes), int(codes2), 0),),
                                                       over)))
    el = topic(p.feed("gw", data, T0 + 0.61), "element")
    assert el["c1"][0] == pytest.approx(sk.params.C1_rest, rel=0.02)
    assert el["c2"][0] == pytest.approx(sk.params.C2_rest, rel=0.02)


def test_tare_retakes_the_baseline() -> None:
    sk = GridFrames()
    p = make({"calibration": {"n_baseline": 5}})
    settle(p, sk, 10)
    press(p, sk, STRADDLE, 10, 5)
    assert p.skin.elements.touched[:2].all()  # type: ignore[union-attr]  # the layout is in place by now
    assert p.tare([1, 2]) == 2
    out = press(p, sk, STRADDLE, 15, 8)  # the press is now part of the baseline
    el = topic(out, "element")
    assert not any(el["touched"])
    assert max(abs(x) for x in el["dc1"]) < 1e-14


def test_layout_file_places_bridges_and_reports_strangers(tmp_path: Path) -> None:
    f = tmp_path / "skin.toml"
    f.write_text(layout_to_toml(grid_layout(1, 2, first_id=1)))
    p = make(layout=load_layout(f))
    sk = GridFrames()
    settle(p, sk, 60)
    out = press(p, sk, None, 60, 2)
    assert sorted(set(topic(out, "element")["bridge"])) == [1, 2]
    h = p.health_body(T0 + 1)
    assert h["unplaced"] == [3, 4]
    assert h["bridges"]["3"]["unmapped_samples"] > 0
    assert h["layout"]["source"] == "file"


def test_hello_layout_and_topology() -> None:
    sk = GridFrames()
    p = make()
    out = p.feed("gw", sk.hellos() + sk.beacons(), T0)
    topo = topic(out, "topology")
    assert topo["layout"]["ids"] == [1, 2, 3, 4]
    ticked = p.tick(T0 + 0.1)
    topo = topic(ticked, "topology")
    assert topo["bridges"]["2"]["parent"] == 1 and topo["bridges"]["2"]["gateway"] == 1
    assert topo["bridges"]["2"]["link"] == "gw" and topo["bridges"]["1"]["alive"]
    assert [t for t, _ in published(p.tick(T0 + 1.2))] == ["health"]  # unchanged: health only
    ticked = p.tick(T0 + 10)  # all silent now: topology changes, silence reported
    assert topic(ticked, "topology")["bridges"]["1"]["alive"] is False
    assert topic(ticked, "health")["silent"] == [1, 2, 3, 4]
    assert any("no data from bridge 1" in text for text in logged(ticked))


def test_stuck_channel_is_reported() -> None:
    sk = GridFrames()
    p = make()
    settle(p, sk, 10)
    k1, k2 = sk.counts_for(None)
    for k in range(10, 400):
        data = encode_stream(Frame(1, 0, 4, sk.seq[4], Data(Mode.COUNTER, (Sample(0, k * 500_000, int(k1[3]),
                                                                                   int(k2[3]), 0),))))
        sk.seq[4] += 1
        p.feed("gw", data, T0 + k / 100)
    stuck = p.health_body(T0 + 4)["layout"]["stuck"]
    assert {"bridge": 4, "channel": 1} in stuck and {"bridge": 4, "channel": 2} in stuck
    assert not any(s["bridge"] == 1 for s in stuck)  # silent since t=0.1 s, which is not stuck


def test_unwanted_topics_are_not_built() -> None:
    sk = GridFrames()
    p = make()
    p.want({"contact"})
    settle(p, sk, 5)
    assert press(p, sk, None, 5, 2) == []


def test_force_and_area_per_reading_are_computed_for_element_subscribers_only() -> None:
    """The inverse per reading is for ``element`` messages alone: without a subscriber to
    them a read skips it (a third of a touched read's time, and a press's contact waits
    behind the read), and the skin frames contacts are estimated on are the same."""
    runs = []
    for topics in ({"contact"}, {"contact", "element"}):
        sk, p = GridFrames(), make()
        p.want(topics)
        settle(p, sk)
        out = press(p, sk, STRADDLE, 60)
        job = p.contact_job(T0 + 0.7)
        assert job is not None and job.snapshot.touched.any()
        runs.append((job.snapshot, [t for t, _ in published(out)]))
    (lean, lean_topics), (full, full_topics) = runs
    assert "element" not in lean_topics and "element" in full_topics
    assert np.array_equal(lean.dc, full.dc, equal_nan=True) and np.array_equal(lean.touched, full.touched)
    assert np.array_equal(lean.t_sample, full.t_sample, equal_nan=True)


def test_reassembly_drops_are_reported_per_bridge() -> None:
    sk = GridFrames()
    p = make()
    settle(p, sk, 5)
    samples = tuple(Sample(0, 10**9 + i, 19600, 15800, 0) for i in range(30))
    frags = fragment(Frame(1, 0, 3, 100, Data(Mode.COUNTER, samples)), tag=4)
    p.feed("gw", encode_stream(frags[1]), T0 + 0.1)  # a later fragment with no first one: dropped
    h = p.health_body(T0 + 0.1)
    assert h["bridges"]["3"]["reassembly_drops"] == 1 and h["bridges"]["2"]["reassembly_drops"] == 0
    assert h["reassembly"]["drops"] == {"no_state": 1}


def test_topology_tracks_status_neighbours_and_the_gateway_of_each_link() -> None:
    from cellbridge.protocol import BridgeStatus, Neighbour

    sk = GridFrames()
    p = make()
    p.feed("gw", sk.hellos() + sk.beacons(), T0)
    st = encode_stream(Frame(3, 0, 4, sk.seq[4], BridgeStatus(3, 12, (Neighbour(3, 11), Neighbour(2, 25)), 0, 1, 0,
                                                                  10**6)))
    p.feed("gw2", st, T0 + 0.05)  # bridge 4 now heard through gateway 3 on the second line
    topo = topic(p.tick(T0 + 0.1), "topology")
    b4 = topo["bridges"]["4"]
    assert b4["parent"] == 3 and b4["link"] == "gw2" and b4["gateway"] == 3
    assert b4["neighbours"] == {"2": 2.5, "3": 1.1}
    assert topo["gateways"] == {"gw": [1], "gw2": [3]}
    _, writes = p.command(int(Op.PING), None, 4, T0 + 0.1, 1.0)
    assert [w.link for w in writes] == ["gw2"]  # commands follow the bridge to its new gateway


def test_every_published_field_is_documented() -> None:
    doc = (Path(__file__).parent.parent / "docs" / "zmq-api.md").read_text()
    sk = GridFrames()
    p = make()
    settle(p, sk, 60)
    out = press(p, sk, STRADDLE, 60, 5) + p.tick(T0 + 2)
    job = p.contact_job()
    assert job is not None
    contact = estimate(p, job, runs=3)  # born after three estimates
    assert contact[1]["contacts"]
    seen: set[str] = set()
    for _, m in published(out) + [contact]:
        seen |= set(m)
        for c in m.get("contacts", []):
            seen |= set(c)
        for group in ("links", "bridges"):
            for entry in m.get(group, {}).values():
                if isinstance(entry, dict):
                    seen |= set(entry)
        if isinstance(m.get("layout"), dict):
            seen |= set(m["layout"])
    missing = sorted(k for k in seen if f"`{k}`" not in doc and f"`{k}:" not in doc and f"`{k} " not in doc)
    assert not missing, f"fields not in docs/zmq-api.md: {missing}"


def _rebooted(p: Pipeline, sk: GridFrames, t_reset: float) -> dict:
    """The skin's bridges boot again at ``t_reset``: numbering from 0, HELLOs, then 20
    samples; the last element message the pipeline published."""
    sk.seq = {b: 0 for b in sk.ids}
    p.feed("gw", sk.hellos(), t_reset)
    out = []
    for k, data in sk.stream(20):
        out = p.feed("gw", data, t_reset + 0.01 + k / sk.rate)
    return topic(out, "element")


def test_bridge_reset_is_followed() -> None:
    """A bridge restarts: sequence numbers and cycle counter from zero, HELLO again."""
    sk = GridFrames()
    p = make()
    t = settle(p, sk, 300)
    sk.cycle0 = 0
    t_reset = t + 1.0
    el = _rebooted(p, sk, t_reset)
    assert len(el["bridge"]) == 4  # nothing taken for a duplicate of the old numbering
    assert el["t_sample"][0] == pytest.approx(t_reset + 0.01 + 19 / sk.rate, abs=0.02)
    h = p.health_body(t_reset + 1)["bridges"]["1"]
    assert h["clock_resets"] == 1 and h["seq_restarts"] == 1


def test_elements_read_just_after_a_calibration_step_are_not_left_out() -> None:
    """Bridge 1's frame always comes in one read, the others' 0.1 ms later in the next:
    the calibrator steps at most every 4 ms, on everything read since its last step."""
    sk = GridFrames()
    p = make({"calibration": {"n_baseline": 5}})
    p.feed("gw", sk.hellos(), T0)
    out: list = []
    for k in range(30):
        press_k = STRADDLE if k >= 20 else None
        parts = sk.slot(k, press_k).split(b"\x00\x00")
        t = T0 + k / sk.rate
        p.feed("gw", parts[0] + b"\x00", t)
        out = p.feed("gw", b"\x00" + b"\x00\x00".join(parts[1:]), t + 1e-4)
    el = topic(out, "element")
    assert el["bridge"] == [2, 3, 4] and el["touched"] == [True, False, False]
    assert not any(math.isnan(x) for x in el["dc1"])  # every element has its baseline
    assert p.skin.elements.touched.tolist() == [True, True, False, False]  # type: ignore[union-attr]  # the layout is in place by now


def test_reconfigure_takes_a_new_layout_and_keeps_hello_geometry() -> None:
    sk = GridFrames()
    p = make()
    settle(p, sk, 5)
    assert p.skin.layout is not None and p.skin.layout.n == 4
    p.reconfigure(p.config, grid_layout(1, 2, first_id=1))  # SIGHUP with a layout file now named
    assert p.skin.from_file and p.skin.layout.n == 2
    assert set(p.skin.geometry) == {1, 2, 3, 4}  # what the bridges said is remembered
    p.reconfigure(p.config, None)  # and the layout file removed again: back to HELLO geometry
    assert p.skin.layout is not None and p.skin.layout.n == 4


def test_contact_worker_warm_up_estimates_a_press() -> None:
    from cellbridge.daemon.core import contacts as physics

    calls = []
    run = physics.ContactStage.run
    def counted(self: physics.ContactStage, snap: Any) -> Any:  # the test counts the runs
        calls.append(run(self, snap))
        return calls[-1]

    physics.ContactStage.run = counted  # type: ignore[method-assign]
    try:
        physics.warm_up()
    finally:
        physics.ContactStage.run = run  # type: ignore[method-assign]  # restored
    (contacts,) = calls
    assert len(contacts) == 1 and contacts[0]["force"] == pytest.approx(1.0, rel=0.05)


def test_host_clock_stepping_back_neither_stops_health_nor_hides_a_dead_bridge() -> None:
    """An NTP step of an hour back: health goes on at its interval, and a bridge that
    stops right after the step is reported silent after bridge_timeout, not an hour later."""
    sk = GridFrames()
    p = make({"health": {"interval": 0.5, "bridge_timeout": 2.0}})
    t = settle(p, sk, 100)
    assert [x for x, _ in published(p.tick(t))] == ["health", "topology"]
    back = t - 3600.0
    ticks = [[x for x, _ in published(p.tick(back + i * 0.1))] for i in range(1, 51)]  # 5 s, no data
    assert sum(x.count("health") for x in ticks) >= 9
    body = p.health_body(back + 5.0)
    assert body["silent"] == [1, 2, 3, 4]
    assert all(not b["alive"] for b in p.topology_body(back + 5.0)["bridges"].values())


def test_after_the_clock_steps_back_no_health_time_lies_in_the_future() -> None:
    """A replay in recorded time whose recording steps back a day (two days' captures
    appended): bridges' times were brought back to the step, but ``uptime`` went
    negative (-86399.9 s) and the link's ``connected_since`` stayed a day ahead."""
    sk = GridFrames()
    p = make()
    p.link_state("gw", True, T0, "")
    t = settle(p, sk, 20)
    p.tick(t)
    back = t - 86400.0
    p.tick(back)
    body = p.health_body(back)
    assert 0.0 <= body["uptime"], body["uptime"]
    link = body["links"]["gw"]
    for key in ("connected_since", "last_data"):
        assert link[key] is not None and link[key] <= back + p.wall_offset, (key, link[key] - back)


def test_every_time_health_and_topology_publish_is_wall_clock_time() -> None:
    """The pipeline runs on the monotonic clock (seconds since boot in the service); what it
    publishes is wall-clock time, and a wall-clock step moves it. Health's per-bridge
    ``first_seen`` and ``last_seen`` went out on the monotonic clock (seconds since boot,
    documented as epoch seconds) and never moved with a step."""
    sk = GridFrames()
    p = make()
    wall = 5_000.0  # wall-clock minus monotonic time
    p.set_wall_offset(wall)
    t = settle(p, sk, 20)
    for step in (0.0, -60.0):
        p.host_clock_step(step)
        offset = wall + step
        h = p.health_body(t)
        for b in h["bridges"].values():
            assert b["first_seen"] == pytest.approx(T0 + offset, abs=1.0) and b["last_seen"] == pytest.approx(t + offset, abs=0.1)
        assert h["links"]["gw"]["last_data"] == pytest.approx(t + offset, abs=0.1)
        for node in p.topology_body(t)["bridges"].values():
            assert node["last_seen"] == pytest.approx(t + offset, abs=0.1)


def test_a_command_sent_before_the_host_clock_steps_back_still_times_out() -> None:
    sk = GridFrames()
    p = make()
    t = settle(p, sk, 20)
    p.tick(t)
    pending, _ = p.command(int(Op.PING), None, 1, t, 1.0)
    back = t - 3600.0
    p.tick(back)
    assert p.commands.done(back + 1.5) == [pending]


def test_bridge_reset_soon_after_start_restarts_its_clock() -> None:
    """A bridge that resets 0.3 s after it started (the counter goes back by less than
    the clock's jump limit): its HELLO numbered 0 restarts the fit, so the new samples'
    times are not the old fit's (half a second off)."""
    sk = GridFrames()
    sk.cycle0 = 0
    p = make()
    t = settle(p, sk, 30)
    t_reset = t + 0.2
    el = _rebooted(p, sk, t_reset)
    assert el["t_sample"][0] == pytest.approx(t_reset + 0.01 + 19 / sk.rate, abs=0.02)
    h = p.health_body(t_reset + 1)["bridges"]["1"]
    assert h["clock_resets"] == 1 and h["seq_restarts"] == 1


def test_a_reload_that_changes_nothing_of_the_skin_keeps_a_held_press() -> None:
    """SIGHUP for log rotation or new client keys: the baselines stay, so a hand resting
    on the skin still reads as touched with its force (it used to vanish: baselines were
    re-taken under the hand). A changed calibration still rebuilds."""
    sk = GridFrames()
    p = make()
    settle(p, sk, 100)
    assert topic(press(p, sk, STRADDLE, 100, 20), "element")["touched"] == [True, True, False, False]
    p.reconfigure(make({"health": {"interval": 3.0}}).config, None)
    el = topic(press(p, sk, STRADDLE, 120, 40), "element")
    assert el["touched"] == [True, True, False, False]
    assert el["force"][0] + el["force"][1] == pytest.approx(3.0, rel=0.05)
    assert p.config.health.interval == 3.0 and p.skin.rebuilds == 1
    p.reconfigure(make({"calibration": {"n_baseline": 20}}).config, None)
    assert p.skin.rebuilds == 1 and p.skin.layout is not None  # a new Skin, built from the HELLO geometry
    assert p.skin.config.calibration.n_baseline == 20
    assert topic(press(p, sk, STRADDLE, 160, 5), "element")["touched"] == [False, False, False, False]


def test_unplaced_origins_silent_for_forget_after_are_forgotten_placed_ones_never() -> None:
    """Thousands of origins the layout does not place (CRC-16 phantoms of a noisy line, a
    stranger's frames) used to stay in every health message forever: health grew without
    bound and each tick walked them all. Silent for ``health.forget_after`` s and not
    placed: forgotten (counted); a placed bridge that dies stays reported silent."""
    sk = GridFrames()
    p = make({"health": {"forget_after": 60.0}})
    t = settle(p, sk, 20)
    buf = b"".join(encode_stream(Frame(src=1, dst=0, origin=o, seq=0,
                                       payload=Data(Mode.COUNTER, (Sample(0, 1000, 100, 100, 0),))))
                   for o in range(100, 3100))
    p.feed("gw", buf, t)
    assert p.health_body(t)["unplaced_count"] == 3000
    p.tick(t + 30.0)
    assert len(published(p.tick(t + 61.0, force=True))[0][1]["bridges"]) == 4
    body = p.health_body(t + 61.0)
    assert body["silent"] == [1, 2, 3, 4] and body["forgotten_bridges"] == 3000
    assert len(p.clock) == 4 and set(p.topology.nodes) == {1, 2, 3, 4}
    again = encode_stream(Frame(src=1, dst=0, origin=100, seq=1,
                                payload=Data(Mode.COUNTER, (Sample(0, 2000, 100, 100, 0),))))
    p.feed("gw", again, t + 62.0)  # a forgotten origin that speaks again is back
    assert "100" in p.health_body(t + 62.0)["bridges"]


def test_a_bridge_joining_late_does_not_retake_the_other_elements_baselines() -> None:
    """A HELLO from a bridge that was not there (booted late) grows the HELLO layout; the
    elements already placed keep their baselines and touch state, so a press being held
    goes on reading as touched with its force (it used to vanish: every baseline was
    re-taken, under the press). A bridge that moved is a new element: its baseline is new."""
    from cellbridge.protocol import Hello

    sk = GridFrames()
    p = make()
    t = settle(p, sk, 100)
    assert topic(press(p, sk, STRADDLE, 100, 20), "element")["touched"] == [True, True, False, False]
    late = Hello(77, "test-1", 0.5, 0.5, float(sk.layout.side), CLOCK, 3)
    p.feed("gw", encode_stream(Frame(src=1, dst=0, origin=77, seq=0, payload=late)), t + 0.21)
    assert p.skin.layout is not None and p.skin.layout.n == 5
    el = topic(press(p, sk, STRADDLE, 121, 40), "element")
    assert el["touched"] == [True, True, False, False]
    assert el["force"][0] + el["force"][1] == pytest.approx(3.0, rel=0.05)
    assert p.health_body(t + 1.0)["layout"]["not_ready"] == [77]
    moved = Hello(4, "test-1", 0.7, 0.7, float(sk.layout.side), CLOCK, 3)
    p.feed("gw", encode_stream(Frame(src=1, dst=0, origin=4, seq=0, payload=moved)), t + 0.62)
    assert p.health_body(t + 1.0)["layout"]["not_ready"] == [4, 77]


def test_sample_rate_is_over_the_time_that_passed_not_the_configured_interval() -> None:
    """Health runs at least ``interval`` apart, often later (a 0.1 s tick, a loaded loop,
    a reload): a bridge's sample_rate divided the samples since the last health by the
    configured interval, so 100 samples/s read as 150 when health came 1.5 s apart."""
    sk = GridFrames()
    p = make({"health": {"interval": 1.0}})
    t = settle(p, sk, 50)
    p.tick(t)
    for k, data in sk.stream(150, start=50):
        p.feed("gw", data, T0 + k / sk.rate)
    body = dict(published(p.tick(t + 1.5)))["health"]
    assert body["bridges"]["1"]["sample_rate"] == pytest.approx(sk.rate)
@pytest.mark.parametrize("max_delay, per_frame, seed", [(2, 1, 3), (4, 1, 4), (2, 5, 5)])
def test_frames_of_one_press_arriving_staggered_give_one_steady_contact(max_delay: int, per_frame: int,
                                                                         seed: int) -> None:
    """A 4x4 skin pressed across the corner of four elements; every bridge samples at its
    own phase (no mesh time: the DATA fallback) and its frames reach the host up to
    ``max_delay`` sample periods late. The press is one contact from its birth to its end,
    and every report is right, or says which elements it does not know and covers the
    truth with its σ: an element whose readings around the frame differ in touch was
    pressed or released between them, perhaps before the frame, and is unknown there (a
    skin half pressed, half not, gave a press on one element)."""
    sk = GridFrames(rows=4, cols=4)
    corner = (0.0585, 0.0625, 3.0, 0.020)  # across the corner of bridges 6, 7, 10 and 11
    p = make({"calibration": {"n_baseline": 10}})  # every element ready before the press, however reads fall
    p.feed("gw", sk.hellos() + sk.beacons(), T0)
    period = 1.0 / sk.rate
    seen: dict[int, list[dict]] = {}
    next_estimate = -math.inf
    w = worker()
    for t, data in staggered(sk, 160, corner, on=80, off=130, max_delay=max_delay * period, per_frame=per_frame,
                             seed=seed):
        now = T0 + 0.001 + t
        p.feed("gw", data, now)
        if now < next_estimate:  # the service's pace: [contact] rate estimates a second
            continue
        next_estimate = now + 1.0 / p.config.contact.rate
        job = p.contact_job()
        if job is None:
            continue
        msg = p.contact_frame(job, w.estimate_now(job)).payload
        for c in msg["contacts"]:
            seen.setdefault(c["id"], []).append(c)
    assert list(seen) == [0], {i: [(c["x"], c["y"], c["force"], c["elements"]) for c in cs] for i, cs in seen.items()}
    reports = [c for c in seen[0] if c["missed"] == 0]
    # the press was seen for most of its 0.5 s: the moment advances a frame of the bridges at a time
    assert len(reports) >= min(25, 0.35 / (per_frame * period))
    whole = [c for c in reports if not c["unknown_near"]]
    assert len(whole) >= len(reports) - 4  # the press's onset and release frames at most
    for c in whole:
        assert sorted(c["elements"]) == [6, 7, 10, 11]
        assert c["force"] == pytest.approx(3.0, rel=0.05)
        assert math.hypot(c["x"] - corner[0], c["y"] - corner[1]) <= 1e-3
        assert T0 + 0.80 <= c["t_sample"] <= T0 + 1.31  # within the press, on the frame's samples
    for c in reports:
        assert abs(c["x"] - corner[0]) <= c["sigma_x"] + 1e-3 and abs(c["y"] - corner[1]) <= c["sigma_y"] + 1e-3


def test_a_silent_bridge_does_not_freeze_contacts() -> None:
    """Bridge 4 stops: the moment waits for it only until it is ``bridge_timeout`` silent."""
    sk = GridFrames()
    p = make({"health": {"bridge_timeout": 0.5}})
    t = settle(p, sk, 60)
    assert snapshot(p) is not None
    for k in range(61, 200):
        frames = sk.slot(k, STRADDLE).split(b"\x00\x00")  # one frame a bridge, bridge 4's last
        p.feed("gw", b"\x00\x00".join(frames[:3]) + b"\x00", T0 + k / sk.rate)
        snap = snapshot(p)
        if T0 + k / sk.rate - t < 0.5 - 0.02:
            assert snap is None  # bridges 1..3 are ahead of the moment bridge 4 reported last
    assert snap is not None and snap.t_frame == pytest.approx(T0 + 199 / sk.rate, abs=0.011)
    assert sorted(snap.ids[snap.touched].tolist()) == [1, 2]


def test_a_bridge_trailing_by_more_than_max_lag_does_not_hold_contacts_back_and_is_reported() -> None:
    """Bridge 4's frames come 0.5 s late; with max_lag 0.3 s the frame does not wait for
    it: its element is unknown (its newest reading is 0.5 s old, far more than a sample
    period), and health names it."""
    sk = GridFrames()
    p = make({"contact": {"max_lag": 0.3}})
    settle(p, sk, 60)
    queue: list[tuple[float, bytes]] = []
    for k in range(61, 160):
        frames = sk.slot(k, STRADDLE).split(b"\x00\x00")
        t = T0 + k / sk.rate
        queue.append((t + 0.5, b"\x00" + frames[3]))
        p.feed("gw", b"\x00\x00".join(frames[:3]) + b"\x00", t)
        while queue and queue[0][0] <= t:
            p.feed("gw", queue.pop(0)[1], t)
    snap = snapshot(p)
    assert snap is not None and snap.t_frame == pytest.approx(T0 + 159 / sk.rate, abs=0.011)
    assert snap.unknown is not None and snap.unknown.tolist() == [False, False, False, True]
    assert math.isnan(snap.t_sample[3])
    layout = p.health_body(T0 + 1.6)["layout"]
    assert layout["late"] == [4] and layout["late_estimates"] >= 1


def _phantoms(sk: GridFrames, forget_after: float, n: int = 3000) -> tuple[Pipeline, float, int]:
    """A pipeline hearing ``sk``, then one junk DATA frame from each of ``n`` origins (100
    on), each with its own sender (CRC-16 phantoms of a noisy line): (pipeline, time, n)."""
    p = make({"health": {"forget_after": forget_after}})
    t = settle(p, sk, 20)
    buf = b"".join(encode_stream(Frame(src=5000 + o, dst=0, origin=o, seq=0,
                                       payload=Data(Mode.COUNTER, (Sample(0, 1000, 100, 100, 0),))))
                   for o in range(100, 100 + n))
    p.feed("gw", buf, t)
    return p, t, n


def test_bogus_origins_cost_health_a_bounded_summary_and_their_gateway_ids_are_pruned() -> None:
    """One junk frame from each of thousands of origins (CRC-16 phantoms, each with a random
    sender) made every health message list each one (15.5 MB at 65 530) for ``forget_after``,
    and their sender ids stayed in topology's gateways for ever. Health now lists every placed
    bridge and at most a bounded number of the others, with their counts; phantom gateway ids
    are pruned when their bridges are forgotten, the real gateway is kept."""
    from cellbridge.daemon.core.health import UNPLACED_SHOWN as _UNPLACED_SHOWN

    sk = GridFrames()
    p, t, n = _phantoms(sk, 60.0)
    h = p.health_body(t + 1.0)
    assert {"1", "2", "3", "4"} <= set(h["bridges"])  # placed bridges always reported
    assert len(h["bridges"]) == 4 + _UNPLACED_SHOWN and h["bridges_not_shown"] == n - _UNPLACED_SHOWN
    assert h["unplaced"] == list(range(100, 100 + _UNPLACED_SHOWN)) and h["unplaced_count"] == n
    topo = p.topology_body(t + 1.0)
    assert topo["gateways"]["gw"][0] == 1 and len(topo["gateways"]["gw"]) == 1 + _UNPLACED_SHOWN
    assert topo["gateways_not_shown"] == n - _UNPLACED_SHOWN
    for k, data in sk.stream(20, start=20):  # the real skin goes on talking
        p.feed("gw", data, t + 60.0 + k / sk.rate)
    p.tick(t + 61.0, force=True)
    h = p.health_body(t + 61.0)
    assert h["unplaced_count"] == 0 and h["bridges_not_shown"] == 0 and h["silent_count"] == 0
    assert p.topology_body(t + 61.0)["gateways"] == {"gw": [1]}  # the gateway heard stays
    p.tick(t + 122.0, force=True)  # and is dropped too once unheard for forget_after: the line is silent
    assert p.topology_body(t + 122.0)["gateways"] == {} and p.health_body(t + 122.0)["silent_count"] == 4


def test_bogus_origins_heard_after_a_tick_that_found_nothing_to_forget_are_still_forgotten() -> None:
    """On a steady skin a health tick finds nothing it could forget and no scan was due
    until a new unplaced origin came; but nothing said so, and every phantom heard after
    that tick stayed for the daemon's life (65 530 of them: 601 s later none forgotten,
    their sender ids still listed as gateways). A new origin or sender id makes the next
    due tick look again."""
    sk = GridFrames()
    p = make({"health": {"forget_after": 60.0}})
    t = settle(p, sk, 20)
    p.tick(t, force=True)  # a steady skin: nothing unplaced, nothing to forget
    for k, data in sk.stream(20, start=20):
        p.feed("gw", data, t + k / sk.rate)
    t += 1.0
    n = 500
    p.feed("gw", b"".join(encode_stream(Frame(src=5000 + o, dst=0, origin=o, seq=0,
                                              payload=Data(Mode.COUNTER, (Sample(0, 1000, 100, 100, 0),))))
                          for o in range(100, 100 + n)), t)
    assert p.health_body(t)["unplaced_count"] == n
    p.tick(t + 30.0, force=True)
    for k, data in sk.stream(20, start=40):  # the real skin goes on talking
        p.feed("gw", data, t + 60.0 + k / sk.rate)
    p.tick(t + 61.0, force=True)
    h = p.health_body(t + 61.0)
    assert h["forgotten_bridges"] == n and h["unplaced_count"] == 0 and h["bridges_not_shown"] == 0
    assert set(p.health.bridges) == {1, 2, 3, 4} and set(p.topology.nodes) == {1, 2, 3, 4}
    assert p.topology_body(t + 61.0)["gateways"] == {"gw": [1]}
    # A second burst, after a tick that again left nothing to forget: forgotten likewise.
    p.feed("gw", encode_stream(Frame(src=6000, dst=0, origin=9000, seq=0,
                                     payload=Data(Mode.COUNTER, (Sample(0, 1000, 100, 100, 0),)))), t + 62.0)
    for k, data in sk.stream(20, start=60):
        p.feed("gw", data, t + 122.0 + k / sk.rate)
    p.tick(t + 123.0, force=True)
    assert p.health_body(t + 123.0)["forgotten_bridges"] == n + 1
    assert p.topology_body(t + 123.0)["gateways"] == {"gw": [1]}


def test_a_gateway_id_that_is_a_placed_bridge_is_dropped_once_unheard_as_a_gateway() -> None:
    """A corrupt frame that passes the CRC names a random link-level sender; when that id is
    a placed bridge's (or a bridge that once held the line no longer does), it was listed as
    the link's gateway for ever, though only the real gateway is heard there. A gateway id
    unheard on its link for ``forget_after`` s is dropped, placed or not; the bridge itself
    stays in topology."""
    sk = GridFrames()
    p = make({"health": {"forget_after": 60.0}})
    t = settle(p, sk, 20)
    p.feed("gw", encode_stream(Frame(src=3, dst=0, origin=2, seq=500, payload=Beacon(1, 10, 1))), t)
    assert p.topology_body(t)["gateways"] == {"gw": [1, 3]}
    for k, data in sk.stream(20, start=20):  # only the real gateway is heard on the line
        p.feed("gw", data, t + 60.0 + k / sk.rate)
    p.tick(t + 61.0, force=True)
    topo = p.topology_body(t + 61.0)
    assert topo["gateways"] == {"gw": [1]}
    assert {"1", "2", "3", "4"} <= set(topo["bridges"])


def test_bogus_origins_cost_a_tick_a_bounded_topology_and_a_bounded_number_of_log_events() -> None:
    """65 530 phantom origins made every tick 0.5 s long: topology listed each one (and its
    sender as a gateway), and when they went quiet each got its own "no data" event. Topology
    now lists every placed bridge and at most ``_UNPLACED_SHOWN`` others (the rest counted),
    and their silence is logged one by one only up to that bound, then as one summary."""
    from cellbridge.daemon.core.health import UNPLACED_SHOWN as _UNPLACED_SHOWN

    sk = GridFrames()
    p, t, n = _phantoms(sk, 600.0)
    for k, data in sk.stream(20):  # the real skin goes on talking
        p.feed("gw", data, t + 9.0 + k / sk.rate)
    out = p.tick(t + 10.0, force=True)
    texts = logged(out)
    assert len(texts) == _UNPLACED_SHOWN + 1
    assert f"{n - _UNPLACED_SHOWN} more bridges" in texts[-1]
    topo = next(body for topic, body in published(out) if topic == "topology")
    assert {"1", "2", "3", "4"} <= set(topo["bridges"])
    assert len(topo["bridges"]) == 4 + _UNPLACED_SHOWN and topo["bridges_not_shown"] == n - _UNPLACED_SHOWN
    assert len(topo["gateways"]["gw"]) == 1 + _UNPLACED_SHOWN and topo["gateways_not_shown"] == n - _UNPLACED_SHOWN
    assert len(msgpack.packb(topo)) < 64_000


def test_contact_ids_are_never_reused_after_the_tracker_is_rebuilt() -> None:
    """Ids restarted at 0 whenever the tracker was built afresh: a replaced contact worker
    (a new process), or a SIGHUP that changed the estimation settings: four presses came
    back as ids [0, 1, 0, 0]. The pipeline keeps the lowest id it never published and every
    job carries it, so a rebuilt tracker numbers a new press from there."""
    from cellbridge.daemon.core import contacts

    sk = GridFrames()
    p = make()
    settle(p, sk)
    ids = []

    def press_and_release(start: int) -> None:
        press(p, sk, STRADDLE, start, 10)
        ids.append(estimate(p, p.contact_job(), runs=3)[1]["contacts"][0]["id"])  # type: ignore[arg-type]  # a contact job is due here
        press(p, sk, None, start + 10, 10)
        assert estimate(p, p.contact_job(), runs=4)[1]["contacts"] == []  # type: ignore[arg-type]  # a contact job is due here

    press_and_release(60)
    contacts._STAGES.clear()  # the worker process was replaced: its trackers are new
    press_and_release(80)
    p.reconfigure(make({"contact": {"birth_frames": 2}}).config, None)  # SIGHUP: estimation changed
    press_and_release(100)
    assert len(set(ids)) == 3 and ids == sorted(ids), ids


@pytest.mark.parametrize("cause", ["late_hello", "worker_replaced", "sighup_contact", "sighup_layout"])
def test_a_contact_held_across_a_rebuild_keeps_its_id(cause: str) -> None:
    """A press held while the contact tracker is rebuilt used to come back under a new id
    (after ``birth_frames`` estimates without it): a late bridge's HELLO changing the
    layout, a replaced worker process, a SIGHUP changing the contact settings or the layout
    file. Each job carries the contacts last published; a tracker built afresh continues
    them (matched by position or element), and the SIGHUP keeps the baselines of elements
    that kept their place, so the held press is the same contact at once."""
    from cellbridge.daemon.core import contacts
    from cellbridge.protocol import Hello
    from cellbridge.tactile import SkinLayout

    sk = GridFrames()
    p = make(layout=sk.layout if cause == "sighup_layout" else None)
    t = settle(p, sk, 100)
    press(p, sk, STRADDLE, 100, 20)
    before = estimate(p, p.contact_job(), runs=3)[1]["contacts"]  # type: ignore[arg-type]
    assert len(before) == 1
    if cause == "late_hello":
        late = Hello(77, "test-1", 0.5, 0.5, float(sk.layout.side), CLOCK, 3)
        p.feed("gw", encode_stream(Frame(src=1, dst=0, origin=77, seq=0, payload=late)), t + 0.21)
        assert p.skin.layout is not None and p.skin.layout.n == 5
    elif cause == "worker_replaced":
        contacts._STAGES.clear()  # a new worker process: no trackers
    elif cause == "sighup_contact":
        p.reconfigure(make({"contact": {"birth_frames": 2}}).config, None)
    else:
        grown = SkinLayout(np.vstack([sk.layout.centres, [[0.5, 0.5]]]), side=sk.layout.side,
                           ids=np.array([*sk.ids, 77]))
        p.reconfigure(make().config, grown)
        assert p.skin.layout is not None and p.skin.layout.n == 5
    press(p, sk, STRADDLE, 120, 20)
    job = p.contact_job()
    assert job is not None
    after = estimate(p, job)[1]["contacts"]
    assert [c["id"] for c in after] == [before[0]["id"]]
    assert after[0]["force"] == pytest.approx(before[0]["force"], rel=0.05)


def _hello(bid: int, x: float, y: float, seq: int = 0) -> bytes:
    from cellbridge.protocol import Hello

    return encode_stream(Frame(src=1, dst=0, origin=bid, seq=seq, payload=Hello(bid, "test-1", x, y, 0.02, CLOCK, 3)))


def test_a_bridge_joining_a_placed_skin_never_displaces_a_placed_one() -> None:
    """A join used to re-place the whole skin in id order: a late bridge with a lower id
    overlapping a placed one took its place (the placed element lost its place, baseline and
    any press on it). A joining bridge is now checked alone against the placed ones: it is
    rejected, and placed once the element in its way moves off."""
    p = make()
    p.feed("gw", _hello(10, 0.0, 0.0) + _hello(11, 0.02, 0.0), T0)
    assert p.skin.layout is not None and p.skin.layout.ids.tolist() == [10, 11]
    p.feed("gw", _hello(5, 0.03, 0.0), T0 + 1.0)  # overlaps 11 by half an element
    assert p.skin.layout.ids.tolist() == [10, 11] and p.skin.rejected == [5]
    assert p.health_body(T0 + 1.0)["layout"]["rejected"] == [5]
    p.feed("gw", _hello(11, 0.1, 0.0, seq=1), T0 + 2.0)  # 11 moves away: 5 fits now
    assert p.skin.layout.ids.tolist() == [5, 10, 11] and p.skin.rejected == []
    assert p.skin.layout.centres.tolist() == [[0.03, 0.0], [0.0, 0.0], [0.1, 0.0]]


def test_a_join_checks_only_the_joining_bridge_whatever_the_skin_size(monkeypatch: pytest.MonkeyPatch) -> None:
    """A join re-placed every bridge (one trial SkinLayout each: ~0.5 s of blocked loop per
    join at 1 000 bridges). Counted, not timed: a join builds one layout, at 10 bridges as at
    400, and its elements keep their baselines."""
    from cellbridge.tactile import SkinLayout

    built = []
    init = SkinLayout.__post_init__

    def counted(self: SkinLayout) -> None:
        built.append(self.centres.shape[0])
        init(self)

    for n in (10, 400):
        p = make()
        p.feed("gw", b"".join(_hello(b, (b % 32) * 0.02, (b // 32) * 0.02) for b in range(1, n + 1)), T0)
        assert p.skin.layout is not None and p.skin.layout.n == n
        monkeypatch.setattr(SkinLayout, "__post_init__", counted)
        built.clear()
        p.feed("gw", _hello(n + 1, ((n + 1) % 32) * 0.02, ((n + 1) // 32) * 0.02), T0 + 1.0)
        assert p.skin.layout.n == n + 1 and built == [n + 1]
        monkeypatch.setattr(SkinLayout, "__post_init__", init)


def test_hello_layout_overlap_check_by_grid_rejects_exactly_the_overlapping_bridges() -> None:
    """The HELLO layout checks each bridge against a grid of its neighbours (a trial layout
    per bridge was O(n² log n): ~1 s of blocked loop per join at 1 000 bridges). The grid
    must reject exactly what a pairwise check in id order rejects: touching edges are fine,
    any overlap in both coordinates is not, whichever cell the centres fall in."""
    from cellbridge.daemon.core.layout import layout_from_geometry

    rng = np.random.default_rng(7)
    side = 0.02
    for _ in range(20):
        pts = np.round(rng.uniform(-0.1, 0.1, (60, 2)) / (side / 4)) * (side / 4)  # many exact touches
        geometry = {i: (float(x), float(y), side) for i, (x, y) in enumerate(pts, start=1)}
        kept: list[int] = []
        for i in sorted(geometry):
            x, y, _ = geometry[i]
            if all(not (abs(x - geometry[j][0]) < side - 1e-9 * side and abs(y - geometry[j][1]) < side - 1e-9 * side)
                   for j in kept):
                kept.append(i)
        layout, rejected = layout_from_geometry(geometry)
        assert layout is not None and layout.ids.tolist() == kept
        assert rejected == sorted(set(geometry) - set(kept))


def test_a_contact_missed_after_a_layout_without_its_elements_is_published_on_the_new_layout() -> None:
    """A SIGHUP whose layout file no longer holds an element under a held press, released
    as the layout changes: the tracker built for the new layout continued the contact, and
    the estimate after the release reported it missed with the elements it had on the old
    layout. The host's contact message looks up each element's row in the frame: a KeyError
    in the contact loop, which ended it (no contact published again, health going on). A
    carried contact keeps only the elements its new layout holds; one with none left ended."""
    from cellbridge.tactile import SkinLayout

    sk = GridFrames()
    p = make(layout=sk.layout)
    settle(p, sk, 100)
    press(p, sk, STRADDLE, 100, 20)  # on the seam of bridges 1 and 2
    w = worker()
    job = p.contact_job()
    assert job is not None
    for _ in range(3):  # (born after a few estimates)
        contacts = w.estimate_now(job)
    before = p.contact_frame(job, contacts).payload["contacts"]
    assert len(before) == 1 and set(before[0]["elements"]) == {1, 2}
    keep = [i for i, b in enumerate(sk.ids) if b != 2]
    smaller = SkinLayout(sk.layout.centres[keep], side=sk.layout.side, ids=sk.layout.ids[keep])
    p.reconfigure(make().config, smaller)  # bridge 2 is no longer placed
    press(p, sk, None, 120, 1)  # released
    job = p.contact_job()
    assert job is not None
    after = p.contact_frame(job, w.estimate_now(job)).payload["contacts"]
    assert [c["id"] for c in after] == [before[0]["id"]] and after[0]["missed"] == 1
    assert after[0]["elements"] == [1] and len(after[0]["cycles"]) == 1


def test_health_stamps_the_last_common_jump_on_the_wall_clock_as_every_other_time() -> None:
    # the pipeline runs on the host's monotonic clock; what it publishes is on the wall clock
    from dataclasses import replace

    sk = GridFrames()
    p = make()
    base = 5_000.0  # a monotonic clock's reading
    p.set_wall_offset(T0 - base)
    p.feed("gw", sk.hellos() + sk.beacons(), base)
    for k, data in sk.stream(60):
        p.feed("gw", data, base + k / sk.rate)
    sk.chip = replace(sk.chip, R_osc=sk.chip.R_osc * 1.02)  # every element steps alike: drift, no touch
    for k, data in sk.stream(10, start=60):
        p.feed("gw", data, base + k / sk.rate)
    body = p.health_body(base + 70 / sk.rate)
    cal = body["layout"]["calibration"]
    assert cal["common_jumps"] >= 1, cal
    t = cal["last_common_jump"]["t"]
    assert T0 + 0.55 <= t <= T0 + 0.7, t  # the step came at slot 60, 0.6 s in

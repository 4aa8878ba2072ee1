"""Mesh topologies in virtual time: delivery, rerouting, loss, loops, duplicates, load sharing."""

from __future__ import annotations

from collections import Counter

import pytest
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, MeshResult, VirtualMesh
from cellbridge.protocol import Data, FrameType, SampleFlags

from support.payloads import payload_as

PERIOD = CLOCK_HZ // 100  # 100 Hz
BEACON_PERIOD = 0.5  # FirmwareConfig.trickle_imax


def missing(result: MeshResult, bridge: int, lo: float, hi: float, period: int = PERIOD) -> int:
    """Samples of ``bridge`` started in [lo, hi) seconds that never reached a gateway.

    On mesh time consecutive samples have consecutive indices; before it (and across the
    switch to it, which moves the bridge's sampling phase by up to one period) their
    cycles are a period apart. At the switch a bridge's first readout record (emulator/
    readout.py) may come after its parent's record of that frame went (the parent did
    not expect it yet): the host does not see that frame of the element (nor does any
    record claim it), so one frame more is allowed there."""
    byc = {s.cycle: s for s in result.samples().get(bridge, []) if lo * CLOCK_HZ <= s.cycle < hi * CLOCK_HZ}
    ss = [byc[c] for c in sorted(byc)]
    if not ss:
        return int((hi - lo) * CLOCK_HZ / period)
    gaps = 0
    for a, b in zip(ss, ss[1:]):
        on_a, on_b = not a.flags & SampleFlags.NO_MESH_TIME, not b.flags & SampleFlags.NO_MESH_TIME
        if on_a and on_b:
            gaps += b.index - a.index - 1
        elif on_a == on_b:
            gaps += round((b.cycle - a.cycle) / period) - 1
        else:
            gaps += max(0, (b.cycle - a.cycle) // period - 2)
    head = (ss[0].cycle - lo * CLOCK_HZ) // period
    tail = (hi * CLOCK_HZ - ss[-1].cycle - 1) // period
    return int(gaps + head + tail)


def assert_complete(result: MeshResult, bridges, lo: float, hi: float, allowed: int = 0,
                    period: int = PERIOD) -> None:
    lost = {b: missing(result, b, lo, hi, period) for b in bridges}
    assert all(v <= allowed for v in lost.values()), lost


def readout_states(result: MeshResult) -> dict[int, dict[int, str]]:
    """bridge -> frame index -> its state in the gateways' READOUT records: ``s`` (a sample),
    ``u`` (unchanged) or ``m`` (missing)."""
    out: dict[int, dict[int, str]] = {}
    for frames in result.gateway_frames.values():
        for f in frames:
            if f.type is FrameType.READOUT:
                r = f.payload
                for x in r.samples:  # type: ignore[union-attr]  # a READOUT frame's payload is a Readout
                    out.setdefault(x.bridge, {})[r.index] = "s"  # type: ignore[union-attr]
                for b in r.unchanged:  # type: ignore[union-attr]
                    out.setdefault(b, {})[r.index] = "u"  # type: ignore[union-attr]
                for b in r.missing:  # type: ignore[union-attr]
                    out.setdefault(b, {}).setdefault(r.index, "m")  # type: ignore[union-attr]
    return out


def assert_known(result: MeshResult, bridges, lo: int, hi: int, share: float) -> None:
    """Every frame index in [lo, hi) of every bridge on the readout (after its first record)
    is in a record (known, or listed missing: never left out), and at least ``share`` known."""
    states = readout_states(result)
    known = total = 0
    for b in bridges:
        st = states.get(b)
        assert st, f"bridge {b}: no readout record"
        for k in range(max(lo, min(st) + 1), hi):
            assert k in st, (b, k)
            total += 1
            known += st[k] in "su"
    assert known >= share * total, (known, total)


def hops_by_origin(result: MeshResult) -> dict[int, set[int]]:
    out: dict[int, set[int]] = {}
    for frames in result.gateway_frames.values():
        for f in frames:
            out.setdefault(f.origin, set()).add(f.hops)
    return out


def test_line_of_8_delivers_every_sample_over_7_hops() -> None:
    mesh = meshgen.line(8)
    r = VirtualMesh(mesh, seed=1).run(4.0)
    assert_complete(r, mesh.ids, 0.5, 3.7)
    assert hops_by_origin(r)[8] == {7}
    assert r.parents == {1: None, 2: 1, 3: 2, 4: 3, 5: 4, 6: 5, 7: 6, 8: 7}
    assert r.cut_off == []
    # HELLO and STATUS from every bridge reach the host
    types = Counter((f.origin, f.type) for f in r.gateway_frames[1])
    assert all(types[(b, FrameType.HELLO)] >= 1 and types[(b, FrameType.STATUS)] >= 1 for b in mesh.ids)


@pytest.mark.parametrize("mesh, settings", [
    (meshgen.grid(4, 4, gateways=(1,)), Settings()),
    (meshgen.ring(12), Settings()),
], ids=["grid4x4", "ring12"])
def test_every_bridge_reaches_the_gateway(mesh, settings) -> None:
    r = VirtualMesh(mesh, seed=3, settings=settings).run(4.0)
    lost = {b: missing(r, b, 0.5, 3.6, CLOCK_HZ // settings.rate_hz) for b in mesh.ids}
    assert all(v == 0 for v in lost.values()), lost
    assert r.total("queue_drops") == 0


def test_a_random_skin_with_shared_cells_reads_out_its_frames() -> None:
    # Cells shared by up to four bridges: the records of one depth go one after another by
    # their rank (no collision among them); a frame lost on the way is listed missing.
    mesh = meshgen.random_mesh(32, seed=2)
    r = VirtualMesh(mesh, seed=3, settings=Settings(rate_hz=50), readout=True).run(4.0)
    on = [b for b in mesh.ids if b in readout_states(r)]
    assert len(on) >= len(mesh.ids) - 2  # the deepest may still be joining mesh time
    assert_known(r, on, 25, 180, 0.999)
    assert r.total("queue_drops") == 0


def test_killing_a_relay_reroutes_within_three_beacon_periods() -> None:
    mesh = meshgen.grid(4, 4, gateways=(1,))
    vm = VirtualMesh(mesh, seed=4)
    before = vm.run(2.0)
    relay = 2 if 2 in before.parents.values() else 5
    children = [b for b, p in before.parents.items() if p == relay]
    assert children
    vm.kill(relay, at=2.0)
    r = vm.run(3.0)
    alive = [b for b in mesh.ids if b != relay]
    assert all(r.parents[b] != relay for b in alive)
    assert_complete(r, alive, 2.0 + 3 * BEACON_PERIOD, 4.7)
    assert r.cut_off == []


def test_bridges_cut_off_by_a_dead_relay_are_reported() -> None:
    mesh = meshgen.line(8)
    vm = VirtualMesh(mesh, seed=5)
    vm.kill(4, at=1.0)
    r = vm.run(4.0)
    assert r.cut_off == [5, 6, 7, 8]
    assert all(r.counters[b]["route_lost"] >= 1 and r.counters[b]["has_route"] == 0 for b in (5, 6, 7, 8))
    assert all(r.counters[b]["has_route"] == 1 for b in (1, 2, 3))
    assert_complete(r, [1, 2, 3], 0.5, 3.7)
    assert all(missing(r, b, 2.0, 3.7) == 170 for b in (5, 6, 7, 8))  # nothing after the cut
    assert set(mesh.ids) - mesh.reachable(dead=frozenset({4})) == {4, 5, 6, 7, 8}


def test_cut_cell_in_a_ring_reroutes_the_other_way() -> None:
    mesh = meshgen.ring(8)
    vm = VirtualMesh(mesh, seed=6)
    vm.cut(1, at=1.0)  # the cell between bridges 1 and 2
    r = vm.run(4.0)
    assert r.parents[2] == 3
    assert_complete(r, mesh.ids, 1.0 + 3 * BEACON_PERIOD, 3.7)


def test_restarted_bridge_comes_back() -> None:
    mesh = meshgen.line(4)
    vm = VirtualMesh(mesh, seed=7)
    vm.kill(3, at=1.0)
    vm.restart(3, at=2.0)
    r = vm.run(4.0)
    assert r.counters[3]["resets"] == 1
    hellos = [f for f in r.gateway_frames[1] if f.type is FrameType.HELLO and f.origin == 3]
    assert len(hellos) >= 2  # once after power-on, once after the restart
    assert_complete(r, [3, 4], 2.0 + 3 * BEACON_PERIOD, 3.7)


def test_one_percent_loss_per_hop_over_8_hops_delivers_999_per_mille() -> None:
    mesh = meshgen.line(9, loss=0.01)  # 8 hops from bridge 9
    r = VirtualMesh(mesh, seed=8).run(10.8)
    sent = 1000  # started in [0.5, 10.5) s; the run goes on long enough for the last to arrive
    delivered = sent - missing(r, 9, 0.5, 10.5)
    assert delivered / sent >= 0.999
    assert hops_by_origin(r)[9] == {8}
    assert r.medium["lost"] > 100 and r.total("retries") > 100  # the loss was real


def test_duplicates_are_suppressed() -> None:
    mesh = meshgen.line(6, loss=0.05)  # lost ACKs make hops retransmit frames already received
    r = VirtualMesh(mesh, seed=9).run(5.0)
    # no frame reaches a gateway twice: named by its number and content, as a new boot's
    # frame that overtook its HELLO (a shorter path) is counted in the old boot here
    keys = [(origin, seq, repr(f.payload)) for origin, _, seq, f in r.delivered()]
    assert len(keys) == len(set(keys))
    assert r.total("duplicates") > 0


def test_no_frame_circulates_in_a_loop_under_churn() -> None:
    mesh = meshgen.random_mesh(24, seed=11, loss=0.02)
    vm = VirtualMesh(mesh, seed=10, settings=Settings(rate_hz=50), readout=False)  # every DATA frame, once
    for i, b in enumerate([5, 9, 14, 3]):
        vm.kill(b, at=1.0 + i)
        vm.restart(b, at=1.5 + i)
    r = vm.run(6.0)
    n = len(mesh.bridges)
    assert max(max(h) for h in hops_by_origin(r).values()) < n
    # no frame reaches a gateway twice: named by its number and content, as a new boot's
    # frame that overtook its HELLO (a shorter path) is counted in the old boot here
    keys = [(origin, seq, repr(f.payload)) for origin, _, seq, f in r.delivered()]
    assert len(keys) == len(set(keys))
    boots = Counter(origin for origin, _, seq, f in r.delivered() if f.type is FrameType.HELLO and seq == 0)
    assert all(boots[b] == 2 for b in (5, 9, 14, 3))  # each restart announced once
    assert_complete(r, mesh.ids, 5.0, 5.7, period=CLOCK_HZ // 50)


def test_two_gateways_share_the_load() -> None:
    mesh = meshgen.line(8, gateways=(1, 8))
    r = VirtualMesh(mesh, seed=12, readout=False).run(4.0)  # DATA frames show each bridge's gateway
    per_gw = {g: Counter(f.origin for f in fr if f.type is FrameType.DATA) for g, fr in r.gateway_frames.items()}
    # each bridge uses the nearer gateway (the middle one either, by hysteresis), never both
    assert {1, 2, 3} <= set(per_gw[1]) and {6, 7, 8} <= set(per_gw[8])
    assert not set(per_gw[1]) & set(per_gw[8])
    assert_complete(r, mesh.ids, 0.5, 3.7)


def test_bit_errors_are_caught_by_crc_and_repaired_by_retries() -> None:
    mesh = meshgen.line(4, ber=2e-4)
    r = VirtualMesh(mesh, seed=13, readout=False).run(4.0)  # DATA frames: retried until through
    assert r.total("rx_crc") > 10
    assert_complete(r, mesh.ids, 0.5, 3.7)


def test_bit_errors_in_the_readout_leave_frames_listed_missing_never_wrong() -> None:
    # A record is retried within its slots: one whose retries all fail is listed missing by
    # the relay above it, and every element-frame is in a record, known or missing.
    mesh = meshgen.line(4, ber=2e-4)
    r = VirtualMesh(mesh, seed=13, readout=True).run(4.0)
    assert r.total("rx_crc") > 10 and r.total("retries") > 0
    assert_known(r, mesh.ids, 50, 370, 0.995)


def test_same_seed_same_run_other_seed_other_run() -> None:
    mesh = meshgen.grid(3, 3, gateways=(1,))

    def stream(seed: int) -> list[tuple[int, int, int]]:
        r = VirtualMesh(mesh, seed=seed).run(1.5)
        return [(f.origin, f.seq, f.hops) for f in r.gateway_frames[1]]

    assert stream(1) == stream(1)
    assert stream(1) != stream(2)


def test_samples_survive_a_restart_then_a_move_to_the_other_gateway() -> None:
    # Bridge 2 restarts while routed to gateway 1, then gateway 1 dies and it moves to
    # gateway 5, which never saw its restart HELLO: samples() must not take its new
    # frames for copies of the old boot's frames that gateway 1 delivered.
    mesh = meshgen.line(5, gateways=(1, 5))
    vm = VirtualMesh(mesh, seed=4, readout=False)  # DATA frames' numbering across a restart
    vm.restart(2, at=2.0)
    vm.kill(1, at=3.0)
    r = vm.run(8.0)
    delivered = {(f.origin, x.cycle) for fr in r.gateway_frames.values() for f in fr
                 if f.type is FrameType.DATA for x in payload_as(f, Data).samples}
    got = r.samples()
    assert {f.origin for f in r.gateway_frames[5] if f.type is FrameType.DATA} >= {2}
    for b in mesh.ids:
        assert len(got[b]) == len({c for o, c in delivered if o == b}), b
    assert len(got[2]) == r.counters[2]["samples_sent"]


def test_grid_routing_stays_stable_under_real_time_message_latency() -> None:
    # A real-time mesh (a process per bridge, the medium relaying datagrams) delivers
    # carrier reports, frames and LINK_ACKs milliseconds late. Late ACKs made bridges
    # re-send frames via a new parent, the copies met higher up with more hops and were
    # taken for loops, each dropping a good parent: parent churn fed by its own copies.
    # Without the latency this grid changes parents ~25 times in 4 s.
    from cellbridge.emulator.firmware.reporting import ReportingMode
    from cellbridge.emulator.mesh.virtual import Latency

    mesh = meshgen.grid(5, 5, gateways=(1,))
    lat = Latency(up=0.003, down=0.003, wake_late=0.002)
    vm = VirtualMesh(mesh, seed=1, settings=Settings(reporting=ReportingMode(40, 1000)), latency=lat,
                     ack_slack=CLOCK_HZ // 100)  # the real-time shell's allowance
    r = vm.run(4.0)
    assert r.total("loops_detected") == 0
    assert r.total("route_lost") == 0 and r.total("frames_failed") == 0
    assert r.total("parent_changes") <= 3 * len(mesh.bridges)
    assert r.total("late_acks") > 0  # the latency was real
    assert r.cut_off == []


def test_latency_model_is_deterministic() -> None:
    from cellbridge.emulator.mesh.virtual import Latency

    def run() -> list[tuple[int, int, int]]:
        vm = VirtualMesh(meshgen.grid(3, 3, gateways=(1,)), seed=2, latency=Latency(seed=5), ack_slack=CLOCK_HZ // 100)
        return [(o, b, s) for o, b, s, _ in vm.run(1.5).delivered()]

    assert run() == run()


def test_an_acknowledged_neighbour_is_alive_though_its_beacons_are_suppressed() -> None:
    """A neighbour expired ``neighbour_timeout`` after its last beacon, while Trickle keeps a
    live one quiet for longer: a parent acknowledging every frame was evicted. An
    acknowledged frame now counts as hearing it; an unacknowledged one does not."""
    from cellbridge.emulator.firmware.routing import Router

    r = Router(me=2, gateway=False, neighbour_timeout=1000)
    r.on_beacon(1, parent=0, path_etx=0, hops=0, tick=0)
    r.on_beacon(3, parent=0, path_etx=0, hops=0, tick=0)
    r.select()
    assert r.parent == 1
    r.on_link_result(1, attempts=1, ok=True, tick=900)
    r.on_link_result(3, attempts=1, ok=False, tick=900)
    r.expire(1500)
    assert set(r.table) == {1} and r.evictions == 1
    r.select()
    assert r.parent == 1 and r.parent_changes == 1


def test_routes_stay_put_on_a_static_lossless_idle_mesh_past_trickles_long_interval() -> None:
    # Neighbours expired 2 s after their last beacon while Trickle suppression kept live
    # ones quiet longer: an 8x8 mesh changed parents 91 times in 30 s, lost routes and
    # evicted live neighbours for ever. After the routes form, a static lossless mesh with
    # nothing to report but heartbeats must keep them (30 s: 60 long intervals): no
    # neighbour evicted, no route lost. A few bridges may still move once to a path
    # cheaper by at least the hysteresis (frames that collided and were retried raise a
    # link's ETX), never back and forth: without the hysteresis, 10 parent changes in
    # those 30 s, one bridge moving twice.
    from cellbridge.emulator.firmware.reporting import ReportingMode

    mesh = meshgen.grid(8, 8, gateways=(1,))
    # unscheduled (every frame of a readout would cost this minute-long run ten times the wakes)
    vm = VirtualMesh(mesh, seed=4, settings=Settings(reporting=ReportingMode(40, 1000)), readout=False)
    formed = vm.run(10.0)
    assert formed.cut_off == []
    end = vm.run(30.0)
    after = {b: {k: end.counters[b].get(k, 0) - formed.counters[b].get(k, 0)
                 for k in ("parent_changes", "route_lost", "neighbour_evictions")} for b in mesh.ids}
    assert sum(a["route_lost"] for a in after.values()) == 0
    assert sum(a["neighbour_evictions"] for a in after.values()) == 0
    assert sum(a["parent_changes"] for a in after.values()) <= len(mesh.ids) // 16
    assert max(a["parent_changes"] for a in after.values()) <= 1
    assert end.cut_off == [] and sum(end.parents[b] != formed.parents[b] for b in mesh.ids) <= len(mesh.ids) // 16

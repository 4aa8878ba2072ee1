"""Mesh time: crystals, the FTSP-style clock of each bridge, and aligned sampling.

Virtual time with crystals drawn within ±50 ppm (and, where it matters, chips whose
counters started at unrelated epochs): every bridge's estimate of global time against
the root's, hop by hop; sync after boot, after a relay dies, after the root dies; the
gate starts of one sample index across a skin.
"""

from __future__ import annotations

import numpy as np
import pytest
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.meshtime import Crystal, MeshClock, MeshClockConfig
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import Mesh
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, VirtualMesh
from cellbridge.protocol import MeshTime, SampleFlags
from hypothesis import given
from hypothesis import strategies as st

from root_return import HOWS, US, How, errors_from_line, root_goes_and_returns, skin_time_line, sync_bound

PERIOD_S = 0.5  # FirmwareConfig.sync_period


# -- the crystal -----------------------------------------------------------------------
@given(st.floats(-100.0, 100.0), st.integers(0, 2**40), st.integers(0, 2**45))
def test_crystal_tick_at_is_the_exact_inverse_of_local(ppm: float, epoch: int, tick: int) -> None:
    c = Crystal(ppm, epoch)
    local = c.local(tick)
    first = c.tick_at(local)
    assert first <= tick and c.local(first) == local and (first == 0 or c.local(first - 1) < local)


def test_crystal_rejects_nonsense() -> None:
    with pytest.raises(ValueError, match="ppm"):
        Crystal(5000.0)
    with pytest.raises(ValueError, match="epoch"):
        Crystal(0.0, -1)


# -- the clock alone -------------------------------------------------------------------
def _feed(clock: MeshClock, root: Crystal, me: Crystal, ticks: list[int], seq0: int = 1, root_id: int = 1) -> None:
    for i, t in enumerate(ticks):
        clock.heard(MeshTime(root_id, (seq0 + i) & 0xFFFF, root.local(t)), me.local(t))


def test_regression_measures_the_skew_and_extrapolates_between_beacons() -> None:
    root, me = Crystal(31.0, 10**9), Crystal(-44.0, 7 * 10**11)
    clock = MeshClock(5, False)
    _feed(clock, root, me, [int(i * 0.5 * CLOCK_HZ) for i in range(1, 9)])
    assert clock.synced(me.local(int(4.2 * CLOCK_HZ)))
    assert abs(clock.skew() - ((1 + 31e-6) / (1 - 44e-6) - 1)) < 1e-8
    for t in (4.3, 4.9, 6.0):  # between and beyond the last beacon
        tick = int(t * CLOCK_HZ)
        assert abs(clock.global_at(me.local(tick)) - root.local(tick)) <= 2
        g = root.local(tick)
        assert abs(me.tick_at(clock.local_at(g)) - tick) <= 2  # and back


def test_an_old_round_is_never_taken_and_the_table_is_bounded() -> None:
    root, me = Crystal(10.0), Crystal(-10.0)
    clock = MeshClock(5, False)
    _feed(clock, root, me, [CLOCK_HZ, 2 * CLOCK_HZ], seq0=10)
    assert not clock.heard(MeshTime(1, 10, root.local(3 * CLOCK_HZ)), me.local(3 * CLOCK_HZ))  # same round again
    assert not clock.heard(MeshTime(1, 5, root.local(3 * CLOCK_HZ)), me.local(3 * CLOCK_HZ))  # older
    assert clock.counters["time_ignored"] == 2
    _feed(clock, root, me, [int((3 + i) * CLOCK_HZ) for i in range(20)], seq0=12)
    assert len(clock._points) == clock.config.table


def test_a_lower_root_takes_over_and_an_outlier_is_not_taken() -> None:
    a, me = Crystal(20.0), Crystal(0.0, 5 * 10**9)
    clock = MeshClock(5, False)
    _feed(clock, a, me, [CLOCK_HZ, 2 * CLOCK_HZ, 3 * CLOCK_HZ], root_id=3)
    t = int(3.5 * CLOCK_HZ)
    # one bad point from the same root: ignored, the fit stays
    assert not clock.heard(MeshTime(3, 9, a.local(t) + 100 * US), me.local(t))
    assert clock.counters["time_outliers"] == 1 and clock.root == 3
    # a lower root: followed at once
    b = Crystal(-20.0, 3 * 10**9)
    assert clock.heard(MeshTime(2, 1, b.local(t)), me.local(t))
    assert clock.root == 2 and clock.counters["root_changes"] == 1


def test_a_gateway_becomes_root_after_the_timeout_and_carries_the_time_on() -> None:
    cfg = MeshClockConfig()
    root, me = Crystal(40.0, 10**10), Crystal(-40.0)
    gw = MeshClock(7, True, cfg, boot_local=0)
    gw.tick(me.local(int(0.1 * CLOCK_HZ)))
    assert not gw.is_root  # listening for a root first
    _feed(gw, root, me, [int(i * 0.5 * CLOCK_HZ) for i in range(1, 6)], root_id=1)
    assert gw.root == 1
    before = gw.global_at(me.local(int(2.5 * CLOCK_HZ)))
    gw.tick(me.local(int(2.6 * CLOCK_HZ)))
    assert gw.root == 1  # not yet timed out
    late = int(2.5 * CLOCK_HZ) + cfg.root_timeout + 10_000  # (counted in its own, slower, cycles)
    gw.tick(me.local(late))
    assert gw.is_root
    # the new root's global time is the estimate it had: no jump against the old root
    assert abs(gw.global_at(me.local(late)) - root.local(late)) < 5 * US
    assert gw.global_at(me.local(int(2.5 * CLOCK_HZ))) == before


def test_a_gateway_that_took_over_ignores_the_dead_roots_echoes() -> None:
    # A neighbour that has not timed out yet still passes the dead root's last round on.
    # The new root took that beacon for "a lower root appears", followed the dead root
    # with a cleared table and ran on its bare crystal: 40 ppm off, 40 us a second.
    cfg = MeshClockConfig()
    root, me = Crystal(40.0, 10**10), Crystal(-40.0)
    gw = MeshClock(7, True, cfg, boot_local=0)
    _feed(gw, root, me, [int(i * 0.5 * CLOCK_HZ) for i in range(1, 6)], seq0=20, root_id=1)  # rounds 20..24
    late = int(2.5 * CLOCK_HZ) + cfg.root_timeout + 10_000
    gw.tick(me.local(late))
    assert gw.is_root
    for seq in (24, 23):  # the last round taken, or an older one: an echo of the dead root
        t = late + CLOCK_HZ // 10
        assert not gw.heard(MeshTime(1, seq, root.local(t) - 30 * US), me.local(t))
    assert gw.is_root and gw.counters["time_echoes"] == 2
    t = late + 2 * CLOCK_HZ
    assert abs(gw.global_at(me.local(t)) - root.local(t)) < 5 * US  # still on the skin's time
    # a bridge that gave the root up (no gateway) takes no echo for its next root either
    br = MeshClock(9, False, cfg)
    _feed(br, root, me, [int(i * 0.5 * CLOCK_HZ) for i in range(1, 6)], seq0=20, root_id=1)
    br.tick(me.local(late))
    assert br.root is None
    assert not br.heard(MeshTime(1, 24, root.local(late)), me.local(late)) and br.root is None
    assert br.heard(MeshTime(7, 25, root.local(late + 1000)), me.local(late + 1000)) and br.root == 7
    # once every neighbour has timed out, the old root's rounds are its own again: a root
    # gateway that rebooted numbers them from 1 and must be heard
    br2 = MeshClock(9, False, cfg)
    _feed(br2, root, me, [int(i * 0.5 * CLOCK_HZ) for i in range(1, 6)], seq0=20, root_id=1)
    br2.tick(me.local(late))
    t = late + cfg.root_timeout + CLOCK_HZ // 10
    assert br2.heard(MeshTime(1, 2, root.local(t)), me.local(t)) and br2.root == 1


def test_a_bridge_without_points_for_stale_after_flags_its_samples() -> None:
    root, me = Crystal(0.0), Crystal(0.0)
    clock = MeshClock(5, False)
    _feed(clock, root, me, [CLOCK_HZ, 2 * CLOCK_HZ])
    assert clock.synced(2 * CLOCK_HZ + clock.config.stale_after)
    assert not clock.synced(2 * CLOCK_HZ + clock.config.stale_after + 1)


# -- the mesh in virtual time ----------------------------------------------------------
def _hops(mesh: Mesh, root: int) -> dict[int, int]:
    return mesh.hops(root)


def _errors(vm: VirtualMesh, root: int) -> dict[int, float]:
    """Each synced bridge's |global time - the root's| now, in microseconds."""
    return vm.time_errors(root)


def _run_and_measure(mesh: Mesh, seconds: float, seed: int, after: float) -> tuple[dict[int, list[float]], dict[int, float]]:
    vm = VirtualMesh(mesh, seed=seed, random_epochs=True)
    root = min(mesh.gateways)
    hops = _hops(mesh, root)
    errs: dict[int, list[float]] = {}
    first: dict[int, float] = {}
    for _ in range(int(seconds * 20)):
        vm.run(0.05)
        now = vm.tick / CLOCK_HZ
        for b, e in _errors(vm, root).items():
            first.setdefault(b, now)
            if now >= after:
                errs.setdefault(hops[b], []).append(e)
    synced_by = {h: max(first.get(b, float("inf")) for b in hops if hops[b] == h) for h in set(hops.values()) if h}
    return errs, synced_by


@pytest.mark.parametrize("name, mesh", [
    ("line of 9 (8 hops)", meshgen.line(9)),
    ("4x4 grid", meshgen.grid(4, 4, gateways=(1,))),
    ("random 32", meshgen.random_mesh(32, seed=3)),
])
def test_mesh_time_error_per_hop_and_sync_after_boot(name: str, mesh: Mesh) -> None:
    errs, synced_by = _run_and_measure(mesh, 12.0, seed=2, after=8.0)
    for h, e in errs.items():
        p99 = float(np.percentile(e, 99))
        assert p99 <= sync_bound(h), (name, h, p99)
    boot_listen = MeshClockConfig().boot_listen / CLOCK_HZ
    for h, t in synced_by.items():  # within 3 beacon periods per hop once the root is root
        assert t <= boot_listen + 3 * PERIOD_S * h + 0.05, (name, h, t)


def test_samples_carry_the_skin_frame_index_and_flag_the_time_before_sync() -> None:
    mesh = meshgen.grid(3, 3, gateways=(1,))
    # DATA samples carry each gate's cycle (a readout record carries none: its frame is its time)
    vm = VirtualMesh(mesh, seed=5, random_epochs=True, readout=False)
    r = vm.run(6.0)
    samples = r.samples()
    for b, ss in samples.items():
        early = [s for s in ss if s.flags & SampleFlags.NO_MESH_TIME]
        late = [s for s in ss if not s.flags & SampleFlags.NO_MESH_TIME]
        assert early and late, b  # every bridge booted without time and then had it
        idx = [s.index for s in late]
        assert idx == sorted(set(idx)), b  # on mesh time the index only grows
    # one index is one instant: the gates of index k started within 20 us of each other
    common = set.intersection(*({s.index for s in ss if not s.flags & SampleFlags.NO_MESH_TIME}
                                for ss in samples.values()))
    assert len(common) > 100
    for k in sorted(common)[-50:]:
        starts = [vm.nodes[b].crystal.tick_at(s.cycle) for b, ss in samples.items() for s in ss
                  if s.index == k and not s.flags & SampleFlags.NO_MESH_TIME]
        assert (max(starts) - min(starts)) / US <= 20.0, k


def test_gate_starts_of_one_index_across_an_8x8_skin_within_20_us() -> None:
    """Mesh time across 14 hops. The bridges sample at 10 Hz: the gates it times are those of
    any rate (the test asks for 100 Hz's), and at 100 Hz the 14 s of 64 chips' sampling cost
    85 s of CPU (450 s, the suite's timeout, beside four CPU burners) for the same spread
    (about 2 us either way); bench/bench_meshtime.py measures it with full traffic."""
    mesh = meshgen.grid(8, 8, gateways=(1,))
    vm = VirtualMesh(mesh, seed=7, random_epochs=True, settings=Settings(rate_hz=10))
    vm.run(14.0)  # 14 hops from the far corner: synced by about 0.6 + 14 * 1.5 s at worst
    assert all(fw.clock.synced(fw.crystal.local(vm.tick)) for fw in vm.nodes.values())
    rate = 100
    for _ in range(5):
        vm.run(0.5)
        k = vm.nodes[1].timebase.first_index(vm.tick, rate) + 10
        starts = [fw.timebase.gate_tick(k, rate) for fw in vm.nodes.values()]
        assert (max(starts) - min(starts)) / US <= 20.0


def test_after_a_relay_dies_its_children_keep_time_through_other_neighbours() -> None:
    mesh = meshgen.grid(4, 4, gateways=(1,))
    vm = VirtualMesh(mesh, seed=3, random_epochs=True)
    vm.kill(6, at=8.0)
    vm.run(8.0 + 3 * PERIOD_S)
    root = min(mesh.gateways)
    hops = _hops(mesh, root)
    for _ in range(20):
        vm.run(0.1)
        for b, e in _errors(vm, root).items():
            assert e <= sync_bound(hops[b]), (b, e)
    assert all(fw.clock.synced(fw.crystal.local(vm.tick)) for fw in vm.nodes.values())


def test_after_the_root_gateway_dies_the_other_gateway_carries_the_time_on() -> None:
    mesh = meshgen.grid(4, 4, gateways=(1, 16))
    vm = VirtualMesh(mesh, seed=4, random_epochs=True)
    vm.run(8.0)
    assert vm.nodes[16].clock.root == 1 and vm.nodes[1].clock.is_root
    g16 = vm.nodes[16]
    vm.kill(1, at=8.0)
    cfg = MeshClockConfig()
    hops = _hops(mesh, 16)
    # while the root is gone and until the other gateway takes over, every bridge
    # extrapolates with the skew it measured: the error stays within the bounds
    for _ in range(int((cfg.root_timeout / CLOCK_HZ + 3 * PERIOD_S) / 0.1)):
        vm.run(0.1)
        r = g16
        g0 = r.clock.global_at(r.crystal.local(vm.tick))
        for b, fw in vm.nodes.items():
            e = abs(fw.clock.global_at(fw.crystal.local(vm.tick)) - g0) / US
            assert e <= sync_bound(hops[b]) + sync_bound(hops[1]), (b, e)
    assert g16.clock.is_root
    assert all(fw.clock.root == 16 for fw in vm.nodes.values())
    for _ in range(10):
        vm.run(0.1)
        errs = _errors(vm, 16)
        assert len(errs) == 14 and max(errs.values()) <= 10.0, errs
    # no bridge restarted its table: the skin's time went on without a jump
    assert sum(fw.clock.counters["time_resyncs"] for fw in vm.nodes.values()) == 0


@pytest.mark.parametrize("how", HOWS)
def test_the_root_gateway_back_after_a_failover_leaves_the_skin_time_unmoved(how: How) -> None:
    # Gateway 1 (the root) is cut off or powered off at 8 s; gateway 16 takes the skin's
    # time on. At 12 s gateway 1 is back: cut off, it stayed a root and its rounds name a
    # lower root than 16; restarted, it boots into a skin that has a root and follows it.
    # Either way the skin's time goes on the line it was on: no bridge jumps by more than
    # the sync bounds, none loses mesh time (a cleared table left bridges unsynced for a
    # round, their samples off mesh time, then on one point and a bare crystal: 27 us off).
    # bench/bench_root_return.py measures the same scenario over seeds.
    mesh, vm = root_goes_and_returns(4, how)
    vm.run(11.5)
    assert vm.nodes[16].clock.is_root
    line = skin_time_line(vm)  # the skin's time while 16 is root: a line in true time
    hops = _hops(mesh, 16)
    for _ in range(60):
        vm.run(0.1)
        # gateway 1 is left out: its own time until it hears the skin (restart), or the root's (cut)
        for b, e in errors_from_line(vm, line).items():
            assert e is not None, (b, vm.tick / CLOCK_HZ)  # synced
            assert e <= sync_bound(hops[b]) + sync_bound(hops[1]), (b, e)
    root = 1 if how == "cut" else 16  # a restarted gateway follows the root it finds
    assert all(fw.clock.root == root for fw in vm.nodes.values())
    errs = _errors(vm, root)
    assert len(errs) == 15 and all(e <= sync_bound(_hops(mesh, root)[b]) for b, e in errs.items()), errs
    assert sum(fw.clock.counters["time_resyncs"] for fw in vm.nodes.values()) == 0

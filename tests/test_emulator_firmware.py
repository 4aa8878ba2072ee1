"""Firmware parts and behaviour: commands, reporting modes, downlink flooding, the world."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import pytest
from cellbridge.emulator.firmware.commands import Settings, execute
from cellbridge.emulator.firmware.reporting import Reporter, ReportingMode
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, VirtualMesh
from cellbridge.emulator.realtime.process_bridge import READOUT_HOP, READOUT_WINDOW
from cellbridge.emulator.world.world import Contact, ScenarioError, World, parse_scenario
from cellbridge.protocol import (
    ADDR_BROADCAST,
    Command,
    CommandReply,
    Data,
    Flags,
    Frame,
    FrameType,
    Mode,
    Op,
    Readout,
    SampleFlags,
    Status,
)
from hypothesis import given
from hypothesis import settings as hsettings
from hypothesis import strategies as st

from support.payloads import payload_as
from support.virtual_prefetch import prefetch_after_sampling

if TYPE_CHECKING:
    from collections.abc import Callable

    from cellbridge.emulator.firmware.linklayer import LinkLayer

HOST = 0


def cmd(seq: int, target: int, op: Op, value: int | None = None, token: int = 1) -> Frame:
    return Frame(0, target, HOST, seq, Command(token, op, value), flags=int(Flags.ACK_REQUEST))


def replies(frames: list[Frame]) -> dict[int, list[CommandReply]]:
    out: dict[int, list[CommandReply]] = {}
    for f in frames:
        if f.type is FrameType.CMD_REPLY:
            out.setdefault(f.origin, []).append(f.payload)  # type: ignore[arg-type]  # a CMD_REPLY frame's payload is a CommandReply
    return out


# -- pure parts ----------------------------------------------------------------------


@pytest.mark.parametrize("op, value, status", [
    (Op.SET_RATE, 250, Status.OK),
    (Op.SET_RATE, 251, Status.BAD_VALUE),  # above the gate limit 1/(2·2 ms)
    (Op.SET_RATE, 0, Status.BAD_VALUE),
    (Op.SET_MODE, 1, Status.OK),
    (Op.SET_MODE, 2, Status.BAD_VALUE),
    (Op.SET_GATE, 50_000, Status.OK),
    (Op.SET_GATE, 10, Status.BAD_VALUE),
    (Op.SET_OVERSAMPLING, 64, Status.OK),
    (Op.SET_OVERSAMPLING, 0, Status.BAD_VALUE),
    (Op.SET_REPORTING, 40 | 500 << 32, Status.OK),
    (Op.SET_REPORTING, 40 | 10**6 << 32, Status.BAD_VALUE),
    (Op.SET_RATE, None, Status.BAD_VALUE),
    (Op.PING, None, Status.OK),
])
def test_execute_checks_every_value(op: Op, value: int | None, status: Status) -> None:
    reply, new = execute(Command(7, op, value), Settings(), CLOCK_HZ, 12345)
    assert reply.status is status and reply.token == 7 and reply.op is op
    assert (new is not None) == (status is Status.OK and op is not Op.PING)
    if op is Op.PING:
        assert reply.value == 12345


def test_gate_change_that_breaks_the_rate_is_refused() -> None:
    s = Settings(rate_hz=250)
    reply, new = execute(Command(1, Op.SET_GATE, 200_000), s, CLOCK_HZ, 0)
    assert reply.status is Status.BAD_VALUE and new is None


def test_reporting_value_round_trip() -> None:
    m = ReportingMode.from_value(40 | 2000 << 32)
    assert (m.threshold, m.heartbeat_ms) == (40, 2000) and m.to_value() == 40 | 2000 << 32
    assert ReportingMode.from_value(0).periodic
    assert ReportingMode.from_value(5).heartbeat_ms == 1000


@hsettings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 65535), st.integers(0, 65535)), min_size=1, max_size=200),
       st.integers(1, 500))
def test_event_reporting_never_hides_a_change_beyond_the_threshold(values, threshold) -> None:
    """Between two sent samples every suppressed one is within the threshold of the last sent."""
    from cellbridge.protocol import Sample

    rep = Reporter(ReportingMode(threshold, 1000), cycles_per_ms=50_000)
    last = None
    n_sent = 0
    for i, (a, b) in enumerate(values):
        s = Sample(0, i * 10, a, b)  # far below the heartbeat
        sent = rep.wants(s)
        n_sent += sent
        if last is None:
            assert sent
        elif not sent:
            for x, y in ((a, last.c1), (b, last.c2)):
                d = abs(x - y)
                assert min(d, 65536 - d) <= threshold
        if sent:
            last = s
    assert rep.suppressed == len(values) - n_sent


def test_event_reporting_sends_the_clean_sample_after_a_part_way_one() -> None:
    """A press that begins during a sample's gates leaves that sample part-way (here 1000 ->
    640 of the way to 600); the next, clean one differs from it by less than the threshold.
    It must be sent all the same, or the host holds the part-way reading as the element's
    value until the next change or heartbeat (a corner press came out light and off-centre
    for a second)."""
    from cellbridge.protocol import Sample

    rep = Reporter(ReportingMode(40, 1000), cycles_per_ms=50_000)
    counts = [1000, 1000, 640, 600, 600, 600]
    sent = [rep.wants(Sample(0, i * 500_000, c, c)) for i, c in enumerate(counts)]
    assert sent == [True, False, True, True, False, False]


def test_event_reporting_sends_where_a_slow_change_came_to_rest() -> None:
    """A press sliding off an element lowers its reading a little per sample; the last
    sample sent for a change can stay up to a threshold from where the reading came to
    rest, and the host held it (the element still touched) until the heartbeat, up to a
    second later. Once the reading settles (3 samples within an eighth of the threshold)
    the settled reading goes out, once."""
    from cellbridge.protocol import Sample

    rep = Reporter(ReportingMode(40, 1000), cycles_per_ms=50_000)
    counts = [600, 600, 650, 690, 700, 730, 760, 790, 800, 801, 800, 800, 801, 800, 800, 800]
    sent = [c for i, c in enumerate(counts) if rep.wants(Sample(0, i * 500_000, c, c))]
    # 600 first; 650 (a change), 690 (its follow); 760 (a change), 790 (its follow); then
    # 800 once settled (790 -> 800 is within the threshold: without settling it stays 790)
    assert sent == [600, 650, 690, 760, 790, 800]
    # noise around a steady reading sends nothing more
    assert all(not rep.wants(Sample(0, (20 + i) * 500_000, 800 + i % 2, 800)) for i in range(20))


# -- the world -----------------------------------------------------------------------


def test_scenario_parsing_and_errors() -> None:
    cs = parse_scenario("[[contact]]\nstart = 1\nduration = 0.5\nposition = [0.0, 0.04]\n"
                        "force = 2.0\ndiameter = 0.02\nvelocity = [0.01, 0]\n")
    assert cs == [Contact(1.0, 0.5, 0.0, 0.04, 2.0, 0.02, 0.01, 0.0)]
    for text, words in [
        ("[[contact]]\nstart = 1\nduration = 1\nposition = [0, 0]\nforce = 1\ndiameter = 0.01\nspin = 2\n",
         "unknown key 'spin'"),
        ("[[contact]]\nstart = 1\nduration = 1\nposition = [0, 0]\ndiameter = 0.01\n", "missing key 'force'"),
        ("[[contact]]\nstart = 1\nduration = 1\nposition = [0, 0]\nforce = -1\ndiameter = 0.01\n", "force"),
        ("[[contact]]\nstart = 1\nduration = 1\nposition = 3\nforce = 1\ndiameter = 0.01\n", "position"),
        ("wind = 3\n", "unknown key 'wind'"),
    ]:
        with pytest.raises(ScenarioError, match=words):
            parse_scenario(text, "s.toml")


def test_world_press_straddling_two_elements_splits_the_response() -> None:
    mesh = meshgen.line(3)
    w = World(mesh, [Contact(0.0, 1.0, 0.02, 0.0, 3.0, 0.02)])  # on the seam of elements 1 and 2
    c1, c2 = w.capacitances(0.5)
    rest1, rest2 = w.rest
    assert c1[0] - rest1 == pytest.approx(c1[1] - rest1, rel=1e-9) and c1[0] > rest1
    assert c1[2] == rest1 and c2[2] == rest2
    c1_late, _ = w.capacitances(1.5)
    assert (c1_late == rest1).all()


def test_moving_contact_moves_the_response() -> None:
    mesh = meshgen.line(3)
    w = World(mesh, [Contact(0.0, 2.0, 0.0, 0.0, 3.0, 0.02, vx=0.04)])  # one pitch a second
    assert w.capacitances(0.1)[0].argmax() == 0
    assert w.capacitances(1.05)[0].argmax() == 1



def test_a_moving_contacts_capacitance_at_a_time_is_the_same_whatever_was_asked_before() -> None:
    # A moving contact is evaluated once per quantum (1 ms). Evaluated at whichever time
    # asked first, an element's capacitance at a gate depended on what was asked before:
    # in a virtual mesh (one world for every bridge) on which bridge sampled first, and on
    # whether a bridge computed its next counts ahead (Sampler.prefetch sensing the next
    # gate) or its sample lazily: a count one off in a 4x4 at 250 Hz.
    mesh = meshgen.line(3)
    press = Contact(0.0, 2.0, 0.0, 0.0, 3.0, 0.02, vx=0.04)
    first, fresh = World(mesh, [press]), World(mesh, [press])
    first.capacitances(1.5002)  # the disk straddles elements 1 and 2: it moves their response
    assert first.capacitances(1.5008)[0].tolist() == fresh.capacitances(1.5008)[0].tolist()

# -- behaviour in a mesh ---------------------------------------------------------------


def test_commands_reach_their_target_and_reply() -> None:
    mesh = meshgen.line(6)
    vm = VirtualMesh(mesh, seed=2)
    vm.host_write(1, cmd(100, 6, Op.PING, token=11), at=1.0)
    vm.host_write(1, cmd(101, 4, Op.SET_RATE, 200, token=12), at=1.1)
    vm.host_write(1, cmd(102, 5, Op.SET_RATE, 999, token=13), at=1.2)
    vm.host_write(1, cmd(103, 3, Op.SET_REPORTING, 40, token=14), at=1.3)
    vm.host_write(1, cmd(103, 3, Op.SET_REPORTING, 40, token=14), at=1.35)  # repeated: done once
    vm.host_write(1, cmd(104, 2, Op.RESET, token=15), at=1.4)
    r = vm.run(3.0)
    rep = replies(r.gateway_frames[1])
    assert [x.token for x in rep[6]] == [11]
    assert rep[6][0].value is not None and rep[6][0].value > 1.0 * CLOCK_HZ
    assert rep[4][0].status is Status.OK
    assert rep[5][0].status is Status.BAD_VALUE
    assert len(rep[3]) == 1 and rep[3][0].status is Status.OK
    assert rep[2][0].op is Op.RESET and r.counters[2]["command_resets"] == 1
    assert set(rep) == {2, 3, 4, 5, 6}  # nobody else answered
    rate4 = [s.cycle for s in r.samples()[4] if 2.0 * CLOCK_HZ <= s.cycle < 2.5 * CLOCK_HZ]
    assert len(rate4) == 100  # 200 Hz for half a second


@pytest.mark.parametrize("lazy", [True, False])
def test_samples_taken_before_a_rate_change_go_out_at_the_rate_they_were_taken_at(lazy: bool) -> None:
    # SET_RATE closes the open batch: its samples were taken at the old rate, yet the
    # DATA payload was labelled with the new one (100 -> 50 Hz: indices 225, 226 of
    # 100 Hz sent as indices of 50 Hz, 4.5 s instead of 2.25 s on mesh time). A host
    # placed them 2 s in the future.
    vm = VirtualMesh(meshgen.line(2), seed=5, lazy_sampling=lazy, readout=False)  # DATA batches
    vm.host_write(1, cmd(101, 2, Op.SET_RATE, 50, token=12), at=2.268)
    vm.host_write(1, cmd(102, 2, Op.SET_RATE, 200, token=13), at=2.947)
    r = vm.run(3.5)
    assert [x.status for x in replies(r.gateway_frames[1])[2]] == [Status.OK, Status.OK]
    rates = set()
    for f in r.gateway_frames[1]:
        if f.origin == 2 and f.type is FrameType.DATA:
            data = payload_as(f, Data)
            for s in data.samples:
                if not s.flags & SampleFlags.NO_MESH_TIME:
                    rates.add(data.rate)
                    # in virtual time a chip's cycles are mesh time to within a crystal's drift
                    assert abs(s.cycle / CLOCK_HZ - s.index / data.rate) < 0.005, (data.rate, s)
    assert rates == {50, 100, 200}


def test_broadcast_command_reaches_every_bridge() -> None:
    mesh = meshgen.grid(3, 3, gateways=(1,))
    vm = VirtualMesh(mesh, seed=3)
    vm.host_write(1, cmd(7, ADDR_BROADCAST, Op.SET_MODE, int(Mode.ADC), token=5), at=1.0)
    r = vm.run(2.5)
    assert set(replies(r.gateway_frames[1])) == set(mesh.ids)
    late = [f for f in r.gateway_frames[1] if f.type is FrameType.DATA and payload_as(f, Data).samples[0].cycle > 1.6 * CLOCK_HZ]
    assert late and all(payload_as(f, Data).mode is Mode.ADC and payload_as(f, Data).oversampling == 16 for f in late)


def _data_rate(vm: VirtualMesh, lo: float, hi: float) -> float:
    frames = vm.result().gateway_frames[1]
    n = sum(1 for f in frames if f.type is FrameType.DATA and lo * CLOCK_HZ <= payload_as(f, Data).samples[0].cycle < hi * CLOCK_HZ)
    return n / (hi - lo)


def test_event_reporting_sends_far_fewer_frames_when_idle_and_reports_every_press() -> None:
    mesh = meshgen.grid(4, 4, gateways=(1,))
    presses = [Contact(2.0 + 0.5 * i, 0.2, x, y, 2.0, 0.02)
               for i, (x, y) in enumerate([(0.0, 0.0), (0.06, 0.04), (0.12, 0.12)])]
    runs = {}
    for mode in ("periodic", "event"):
        vm = VirtualMesh(mesh, seed=4, world=World(mesh, list(presses)))
        if mode == "event":
            vm.host_write(1, cmd(1, ADDR_BROADCAST, Op.SET_REPORTING, 40 | 1000 << 32), at=0.2)
        vm.run(4.5)
        runs[mode] = vm
    idle = {m: _data_rate(vm, 0.5, 2.0) for m, vm in runs.items()}
    assert idle["event"] < 0.1 * idle["periodic"]
    r = runs["event"].result()
    samples = r.samples()
    world = runs["event"].world
    for p in presses:
        c1, _ = world.capacitances(p.start + 0.1)
        pressed = [b for b, v in zip(mesh.ids, c1) if v > world.rest[0] * 1.02]
        assert pressed
        for b in pressed:
            tick = runs["event"].nodes[b].crystal.tick_at  # a sample's cycle is its own crystal's
            during = [s for s in samples[b] if p.start * CLOCK_HZ <= tick(s.cycle) < (p.start + p.duration) * CLOCK_HZ]
            base = [s for s in samples[b] if tick(s.cycle) < p.start * CLOCK_HZ][-1]
            # (on mesh time a gate may start at the very instant the press does: all of them count)
            assert during and min(s.c1 for s in during) < base.c1 - 40  # more C, fewer counts
    assert r.total("suppressed") > 0


@pytest.mark.parametrize("op, value", [(Op.SET_RATE, 50), (Op.SET_GATE, 50_000),
                                       (Op.SET_REPORTING, 5 | 100 << 32)])
def test_lazy_sampling_keeps_the_samples_due_before_a_command(op: Op, value: int) -> None:
    # Lazy sampling computes periodic samples only when their frame is due; a command
    # that changes the schedule must not drop (or re-measure) the samples taken before
    # it: the host sees exactly what gate-by-gate sampling gives.
    def run(lazy: bool) -> dict[int, list]:
        vm = VirtualMesh(meshgen.line(3), seed=3, lazy_sampling=lazy)
        vm.host_write(1, cmd(1, 3, op, value), at=2.31)
        return vm.run(3.0).samples()

    lazy, eager = run(True), run(False)
    assert len(lazy[3]) == len(eager[3])
    assert lazy == eager


def test_event_reporting_lazy_sampling_sends_what_gate_by_gate_sampling_sends() -> None:
    # The real-time bridge computes event-based samples lazily (once per frame, not per
    # gate): the frames, their samples and their times on the cell must be exactly those
    # of gate-by-gate sampling, presses included (the capacitance is the one at the gate).
    mesh = meshgen.line(3)
    presses = [Contact(0.8, 0.3, 0.04, 0.0, 2.0, 0.02), Contact(1.6, 0.05, 0.08, 0.0, 4.0, 0.02)]

    def run(lazy: bool) -> tuple[dict, dict]:
        vm = VirtualMesh(mesh, seed=5, world=World(mesh, list(presses)), lazy_sampling=lazy,
                         settings=Settings(reporting=ReportingMode(40, 300)))

        return vm.run(2.5).samples(), vm.serial_chunks  # (tick, bytes) on each gateway's serial line

    (lazy_samples, lazy_frames), (eager_samples, eager_frames) = run(True), run(False)
    pressed = [s for s in eager_samples[2] if 0.8 * CLOCK_HZ <= s.cycle < 1.2 * CLOCK_HZ]
    assert len(pressed) >= 2  # the press and its release were reported
    assert lazy_samples == eager_samples
    assert lazy_frames == eager_frames


@pytest.mark.parametrize("bridges, seed", [(3, 0), (3, 2), (3, 3), (4, 0), (4, 2)])
def test_lazy_sampling_sends_what_gate_by_gate_sampling_sends_from_boot(bridges: int, seed: int) -> None:
    # Booting skins, aligned batches. Line of 3: a bridge that gains mesh time while a
    # timed batch (samples without mesh time) waits puts the next sample in an aligned
    # batch, and the timed one must still leave at its ``max_latency``; lazily it waited
    # for the next gate. Line of 4: a relay whose beacon went out while a child's frame
    # waited in its queue handed that frame to the radio only at its next wake (the next
    # gate gate-by-gate, the next batch's slot lazily). Either way: other frames, other
    # collisions, and a real-time (lazy) relay sat on its children's frames.
    def run(lazy: bool) -> tuple[dict, dict]:
        vm = VirtualMesh(meshgen.line(bridges), seed=seed, lazy_sampling=lazy)

        return vm.run(2.5).samples(), vm.serial_chunks  # (tick, bytes) on each gateway's serial line

    (lazy_samples, lazy_frames), (eager_samples, eager_frames) = run(True), run(False)
    assert lazy_samples == eager_samples
    assert lazy_frames == eager_frames


def test_counters_never_go_back_across_a_reset_command() -> None:
    # A RESET rebuilds the link, radio and router; the totals a user reads must keep
    # what earlier lives counted (only states such as queue_len start again).
    vm = VirtualMesh(meshgen.line(3), seed=3)
    vm.host_write(1, cmd(1, 3, Op.RESET), at=2.0)
    before = vm.run(1.99).counters[3]
    after = vm.run(0.5).counters[3]
    assert after["command_resets"] == 1 and after["resets"] == 1
    for k, v in before.items():
        if k not in ("queue_len", "has_route", "alive"):
            assert after.get(k, 0) >= v, k
    assert after["transmissions"] > before["transmissions"]


def test_a_reset_counts_the_frames_and_samples_it_discards() -> None:
    # A bridge without a route holds its HELLO, DATA and the RESET's reply in its queue;
    # the reset loses them, as a real one would, but never silently.
    from cellbridge.emulator.firmware.firmware import Firmware, FirmwareConfig
    from cellbridge.emulator.mesh.virtual import default_chip
    from cellbridge.protocol import encode

    fw = Firmware(FirmwareConfig(5, (1,)), default_chip(5, 0))
    for t in range(0, CLOCK_HZ, CLOCK_HZ // 100):
        fw.advance(t)
    fw.receive(encode(cmd(1, 5, Op.RESET)), CLOCK_HZ, 1)
    assert len(fw.link.queue) >= 3  # HELLO, DATA, the RESET's reply: no route to send them
    while fw.counters["command_resets"] == 0:
        fw.advance(fw.next_tick)
    c = fw.counters_snapshot()
    assert c["power_off_frames"] >= 3
    # every sample taken is sent, still batched, or counted as discarded
    assert c["samples"] == c.get("samples_sent", 0) + fw.sampler.unsent + c["power_off_samples"]
    assert c["power_off_samples"] > 0
    assert fw.link.queue[0].seq == 0 and fw.link.queue[0].type == FrameType.HELLO  # numbering from 0, HELLO first


def test_a_host_flooding_commands_is_bounded_and_counted() -> None:
    # A host (or garbage that decodes) writing thousands of CMDs for bridges nobody
    # knows: the gateway keeps a bounded number of flood copies and counts each command
    # it could not repeat; every command is accounted for.
    from cellbridge.protocol import encode_stream

    vm = VirtualMesh(meshgen.line(3), seed=3)
    vm.run(0.5)
    gw = vm.nodes[1]
    n = 2000
    gw.serial_in(b"".join(encode_stream(cmd(i, 999, Op.PING)) for i in range(1, n + 1)), vm.tick)
    assert len(gw.floods) <= 48
    assert gw.counters["flooded"] + gw.counters["flood_drops"] == n
    r = vm.run(1.0)
    assert r.counters[1]["flood_drops"] > 0
    assert r.counters[2]["flooded"] == r.counters[1]["flooded"]  # those it repeated reached the next bridge


def test_only_a_boot_sends_a_hello_numbered_0_even_after_the_numbering_wraps() -> None:
    # A HELLO numbered 0 tells the host's duplicate filter that the bridge restarted; a
    # periodic HELLO that happened to fall on seq 0 after a wrap would be taken as one.
    from cellbridge.emulator.firmware.firmware import Firmware, FirmwareConfig
    from cellbridge.emulator.mesh.virtual import default_chip
    from cellbridge.protocol import StreamDecoder

    fw = Firmware(FirmwareConfig(1, (1,), gateway=True), default_chip(1, 0))
    t = CLOCK_HZ
    fw.advance(t)
    fw.seq = 0  # a long run's numbering has just wrapped
    fw.hello_at = t
    fw.advance(t)
    while t < 2 * CLOCK_HZ:
        t = fw.next_tick
        fw.advance(t)
    frames = StreamDecoder().feed(fw.take_serial())
    hellos = [f.seq for f in frames if f.type is FrameType.HELLO]
    assert hellos[0] == 0  # the boot's
    assert len(hellos) == 2 and hellos[1] != 0  # the periodic one, not numbered 0
    assert 0 in [f.seq for f in frames[1:]]  # the wrap itself went ahead


def test_mesh_result_keeps_every_sample_across_the_sequence_wrap() -> None:
    # (origin, boot, seq) must name one frame in a long run: after 65536 frames the
    # numbering wraps without a reset, and samples() must not take the new frames for
    # copies of the boot's first ones.
    vm = VirtualMesh(meshgen.line(3), seed=3, readout=False)  # DATA frames' numbering
    vm.run(1.0)
    for last in (False, False, True):  # a long run's numbering, in steps the filters follow
        for b in (2, 3):
            vm.nodes[b].seq = 0xFFFF - 100 if last else vm.nodes[b].seq + 30000
        vm.run(1.0)
    r = vm.run(10.0)
    assert all(vm.nodes[b].seq < 2000 for b in (2, 3))  # wrapped
    got = r.samples()
    for b in (1, 2, 3):
        sent = r.counters[b]["samples_sent"]
        assert sent > 1000
        # every frame sent has arrived, but for one still on its way when the run ends
        assert 0 <= sent - len(got[b]) <= vm.nodes[b].sampler.aligned_batch()
        on_time = [s.index for s in got[b] if not s.flags & SampleFlags.NO_MESH_TIME]
        assert on_time == list(range(on_time[0], on_time[0] + len(on_time)))  # none lost, none twice


def test_set_gate_beyond_what_the_host_can_unwrap_is_refused() -> None:
    # tactile.transfer.check_gate: beyond max_gate_cycles a press and a counter wrap
    # look alike. The bridge refuses such a gate instead of sending ambiguous counts.
    from cellbridge.tactile.transfer import max_gate_cycles

    vm = VirtualMesh(meshgen.line(2), seed=1)
    limit = max_gate_cycles(chip=vm.nodes[2].chip.params)  # type: ignore[attr-defined]  # the virtual mesh's chips are emulator Chips
    vm.host_write(1, cmd(1, 2, Op.SET_RATE, 10, token=1), at=0.5)
    vm.host_write(1, cmd(2, 2, Op.SET_GATE, limit + 1, token=2), at=0.6)
    vm.host_write(1, cmd(3, 2, Op.SET_GATE, 1_000_000, token=3), at=0.7)
    vm.host_write(1, cmd(4, 2, Op.SET_GATE, limit, token=4), at=0.8)
    r = vm.run(2.0)
    got = {c.token: c.status for c in replies(r.gateway_frames[1])[2]}
    assert got == {1: Status.OK, 2: Status.BAD_VALUE, 3: Status.BAD_VALUE, 4: Status.OK}
    late = [s for s in r.samples()[2] if s.cycle > 0.9 * CLOCK_HZ]
    overflow = SampleFlags.OVERFLOW_C1 | SampleFlags.OVERFLOW_C2
    assert late and not any(s.flags & overflow for s in late)  # at the limit: no counter wraps


def test_a_gateway_counts_the_garbage_the_host_writes() -> None:
    # Bytes on the serial line that are not frames are dropped, as the UART's decoder
    # must, but counted by cause; the command after the garbage is still executed.
    import random as _random

    from cellbridge.emulator.firmware.firmware import Firmware, FirmwareConfig
    from cellbridge.emulator.mesh.virtual import default_chip
    from cellbridge.protocol import StreamDecoder, encode_stream

    fw = Firmware(FirmwareConfig(1, (1,), gateway=True), default_chip(1, 0))
    fw.advance(CLOCK_HZ // 10)
    garbage = _random.Random(1).randbytes(5000) + b"\x00" + b"\x05\x01\x02\x03\x04\x00" + b"\x01" * 600 + b"\x00"
    fw.serial_in(garbage + encode_stream(cmd(1, 1, Op.PING, token=9)), CLOCK_HZ // 10)
    c = fw.counters_snapshot()
    assert c["serial_rx_bytes_dropped"] >= 4000
    assert c.get("serial_rx_overlong", 0) >= 1
    assert sum(v for k, v in c.items() if k.startswith("serial_rx_") and k != "serial_rx_bytes_dropped") >= 2
    out = StreamDecoder().feed(fw.take_serial())
    assert [payload_as(f, CommandReply).token for f in out if f.type is FrameType.CMD_REPLY] == [9]


def test_event_reporting_with_threshold_0_sends_every_change_only() -> None:
    # docs/protocol.md: value 0 is periodic; any other value is event-based, threshold
    # in bits 0-31, so 0 | H << 32 sends a sample when it differs at all (or H passed),
    # and identical samples are suppressed (but for the one right after a change).
    from cellbridge.protocol import Sample

    m = ReportingMode.from_value(500 << 32)
    assert not m.periodic and (m.threshold, m.heartbeat_ms) == (0, 500)
    assert m.to_value() == 500 << 32
    rep = Reporter(m, cycles_per_ms=50_000)
    sent = [rep.wants(Sample(0, i * 500_000, c, 100)) for i, c in enumerate([7, 7, 7, 8, 8, 7])]
    assert sent == [True, False, False, True, True, True]
    assert rep.suppressed == 2
    assert ReportingMode.from_value(0).periodic and ReportingMode.from_value(0).to_value() == 0


def test_a_broadcast_reset_is_answered_by_every_bridge() -> None:
    # A bridge resets once its reply and its copies of the command have left (at most
    # 3 s later), not after a fixed 50 ms: relays that reset at once threw away the
    # replies of the bridges behind them, and the host could not tell who had reset.
    from cellbridge.emulator.firmware.commands import Settings as _Settings

    mesh = meshgen.grid(6, 6, gateways=(1,))
    vm = VirtualMesh(mesh, seed=4, settings=_Settings(rate_hz=20))  # not saturated
    vm.host_write(1, cmd(1, ADDR_BROADCAST, Op.RESET, token=5), at=2.0)
    r = vm.run(8.0)
    got = replies(r.gateway_frames[1])
    assert set(got) == set(mesh.ids)
    assert all([c.token for c in v] == [5] for v in got.values())
    assert r.total("command_resets") == len(mesh.ids)
    assert r.total("power_off_frames") == 0  # nothing was held at the reset
    boots = [f.origin for f in r.gateway_frames[1] if f.type is FrameType.HELLO and f.seq == 0]
    assert all(boots.count(b) == 2 for b in mesh.ids)  # power-on, then the reset: HELLO 0 each


# -- link layer and loop detection under message latency (real-time meshes) -------------

def _link() -> LinkLayer:
    import random

    from cellbridge.emulator.firmware.linklayer import LinkLayer
    from cellbridge.emulator.firmware.transceiver import Transceiver

    link = LinkLayer(5, (1, 2), Transceiver(random.Random(3)), ack_slack=CLOCK_HZ // 100)
    from cellbridge.protocol import Raw
    assert link.enqueue(Raw(int(FrameType.DATA), 0, 20, 9, 2, 0, b""))
    return link


def _due(link: LinkLayer) -> int:
    """The link's next tick: these tests ask it only with a frame pending."""
    tick = link.next_tick
    assert tick is not None
    return tick


def _next_transmission(link, tick: int, parent: int, neighbours: set[int]) -> tuple[int, int]:
    """Run the link until it puts a frame on the cells: (tick, link destination)."""
    from cellbridge.protocol import peek as parse

    for _ in range(100):
        out, _used = link.advance(tick, parent, 0, 10, neighbours)
        if out is not None:
            peeked = parse(out[0])
            assert peeked is not None, out
            return tick, peeked[1]
        tick = link.next_tick
    raise AssertionError("nothing was sent")


def test_a_parent_change_while_waiting_for_an_ack_retries_the_old_next_hop() -> None:
    # The old parent most likely has the frame (its ACK is late or lost); sending it to the
    # new parent too puts a second copy on another path, which meets the first higher up
    # with more hops: a false loop there, a dropped parent, more copies (real-time churn).
    link = _link()
    t, dst = _next_transmission(link, 0, 2, {2, 3})
    assert dst == 2
    t, dst = _next_transmission(link, _due(link), 3, {2, 3})  # parent is now 3
    assert dst == 2 and link.counters["frames_requeued"] == 0
    assert link.acked(20, 9, 2) and link.inflight is None


def test_a_parent_change_sends_the_frame_to_the_new_parent_when_the_old_one_is_gone() -> None:
    link = _link()
    _next_transmission(link, 0, 2, {2, 3})
    t, dst = _next_transmission(link, _due(link), 3, {3})  # 2 evicted: dead or a loop
    assert dst == 3 and link.counters["frames_requeued"] == 1
    assert link.counters["tx_failed"] == 0  # a gone next hop is no link failure to count again


def test_a_late_ack_withdraws_the_retransmission_still_waiting_for_the_cell() -> None:
    # In a real-time mesh the LINK_ACK can arrive after the deadline, once the retransmission
    # is contending: it is late, not lost, and the frame needs no second transmission.
    link = _link()
    _next_transmission(link, 0, 2, {2})
    deadline = _due(link)
    out, _ = link.advance(deadline, 2, 0, 10, {2})
    assert out is None and not link.radio.idle and link.counters["retries"] == 1  # contending
    assert link.acked(20, 9, 2)
    assert link.inflight is None and link.radio.idle and link.counters["late_acks"] == 1
    assert link.next_tick is None  # nothing more to send
    assert link.results == [(2, 1, True)]


def test_a_frame_queued_behind_a_record_contends_once_the_record_is_on_the_cell() -> None:
    # A relay computing its readout sample at its children's records wakes only for them,
    # and each such wake makes a record, which goes before any frame in the queue. A frame
    # queued meanwhile (a HELLO, a STATUS, a DATA of samples from before mesh time, a
    # child's frame to forward) must contend once the record is on the cell, not at a wake
    # not for a record (a DATA frame waited 180 ms in a lossy 3x3; it could wait for ever).
    import random

    from cellbridge.emulator.firmware.linklayer import LinkLayer
    from cellbridge.emulator.firmware.transceiver import Transceiver
    from cellbridge.protocol import Raw

    link = LinkLayer(5, (1, 2), Transceiver(random.Random(3)), ack_slack=CLOCK_HZ // 100)
    link.urgent_acks = False  # as the real-time shells run the readout
    link.enqueue_urgent(Raw(int(FrameType.READOUT), 0, 5, 1, 0, 0, b""), 0)
    assert link.enqueue(Raw(int(FrameType.DATA), 0, 20, 9, 2, 0, b""))
    t, dst = _next_transmission(link, 0, 2, {2})
    assert dst == 2 and link.counters["urgent_sent"] == 1 and link.queue
    t, dst = _next_transmission(link, _due(link), 2, {2})  # no other wake needed
    assert dst == 2 and not link.queue and link.inflight is not None and link.inflight.attempts == 1


def test_an_ack_for_a_frame_never_sent_is_ignored() -> None:
    link = _link()
    out, _ = link.advance(0, 2, 0, 10, {2})  # handed to the radio, still contending
    assert out is None and link.inflight is not None and link.inflight.attempts == 0
    assert not link.acked(20, 9, 2)  # an ACK for another transmission of that frame


def _routed(me: int = 5):
    from cellbridge.emulator.firmware.firmware import Firmware, FirmwareConfig
    from cellbridge.emulator.mesh.virtual import default_chip
    from cellbridge.protocol import ADDR_BROADCAST, Beacon, Frame, encode

    fw = Firmware(FirmwareConfig(me, (1, 2, 3)), default_chip(me, 0))
    fw.receive(encode(Frame(1, ADDR_BROADCAST, 1, 1, Beacon(0, 0, 0))), CLOCK_HZ // 10, 1)
    assert fw.router.parent == 1
    return fw


def _data(origin: int, seq: int, hops: int, src: int, dst: int = 5) -> bytes:
    from cellbridge.protocol import Flags, Raw
    from cellbridge.protocol import reframe as build

    return build(Raw(int(FrameType.DATA), 0, origin, seq, hops, 0, b""), src, dst, int(Flags.ACK_REQUEST))


def test_a_copy_two_hops_longer_is_a_detour_not_a_loop() -> None:
    # The same frame via two children, the second two hops longer (its sender re-sent it
    # via another neighbour): a duplicate, not a loop; the parent is kept.
    fw = _routed()
    tick = CLOCK_HZ // 5
    assert fw.receive(_data(20, 9, 3, src=7), tick, 2)
    assert fw.receive(_data(20, 9, 5, src=8), tick + CLOCK_HZ // 100, 3)
    assert fw.counters["duplicates"] == 1 and fw.counters["loops_detected"] == 0
    assert fw.router.parent == 1


def test_a_copy_three_hops_longer_went_round_a_loop() -> None:
    # A loop through us has at least three bridges (two-bridge loops are broken when the
    # parent sends us a frame): that copy still makes us drop the parent.
    fw = _routed()
    tick = CLOCK_HZ // 5
    assert fw.receive(_data(20, 10, 3, src=7), tick, 2)
    assert fw.receive(_data(20, 10, 6, src=8), tick + CLOCK_HZ // 100, 3)
    assert fw.counters["loops_detected"] == 1
    assert fw.router.parent is None  # dropped until heard again


def test_late_acks_lengthen_the_wait_for_the_next_ones() -> None:
    # A fixed allowance for the ACK is too short when a real-time host is busy: each late
    # ACK costs a retransmission that loads the cells. The wait grows with the lateness
    # seen (and decays while ACKs are timely); where ACKs are never late it stays 0.
    from cellbridge.protocol import Raw

    link = _link()
    t, _ = _next_transmission(link, 0, 2, {2})
    first_wait = _due(link) - link.radio.tx_until
    deadline = _due(link)
    link.advance(deadline, 2, 0, 10, {2})  # the retransmission is contending
    late = CLOCK_HZ // 500  # the ACK comes 2 ms after the deadline
    assert link.acked(20, 9, 2, deadline + late)
    assert link.extra_wait == 2 * late
    assert link.enqueue(Raw(int(FrameType.DATA), 0, 20, 10, 2, 0, b""))
    _next_transmission(link, deadline + late, 2, {2})
    assert _due(link) - link.radio.tx_until == first_wait + 2 * late
    assert link.acked(20, 10, 2, _due(link) - 1)  # in time: the extra wait decays
    assert 0 < link.extra_wait < 2 * late


def test_a_fragmented_control_frame_is_counted_not_a_crash() -> None:
    # BEACON, LINK_ACK and CMD always fit one frame; one flagged FRAGMENT (from a hostile
    # neighbour on the cell, or the host on a gateway's serial line) decoded to a Fragment
    # payload and the firmware died on its missing fields, taking the bridge process down.
    from cellbridge.emulator.firmware.firmware import Firmware, FirmwareConfig
    from cellbridge.emulator.mesh.virtual import default_chip
    from cellbridge.protocol import Fragment, encode, encode_stream

    fw = Firmware(FirmwareConfig(2, (1,)), default_chip(2, 0))
    gw = Firmware(FirmwareConfig(1, (1,), gateway=True), default_chip(1, 0))
    for t in (FrameType.BEACON, FrameType.LINK_ACK, FrameType.CMD):
        frag = Frame(1, ADDR_BROADCAST if t is FrameType.BEACON else 2, 1, 7, Fragment(t, 3, 0, 9, b"\x93\x00\x00\x00"))
        assert fw.receive(encode(frag), CLOCK_HZ, 1) is False
        fw.advance(CLOCK_HZ)
    assert fw.counters["rx_fragmented_control"] == 3
    cmd = Frame(0, 1, 0, 9, Fragment(FrameType.CMD, 3, 0, 9, b"\x93\x00\x00\x00"))
    gw.serial_in(encode_stream(cmd), CLOCK_HZ)
    gw.advance(CLOCK_HZ)
    assert gw.counters["serial_fragmented_control"] == 1


def test_aligned_batches_leave_in_depth_slots_deepest_first() -> None:
    # A line of 4: bridge b is b - 1 hops from the gateway. Each closed batch leaves
    # (slot_depths - depth) * depth_slot after the close (plus <= 1 ms): the deepest first,
    # so at the gateway every batch arrives deepest first, the gateway's own last, and the
    # gateway's own leaves 6 * 4 ms after its close, not at once.
    from cellbridge.protocol import StreamDecoder
    vm = VirtualMesh(meshgen.line(4), seed=3, readout=False)  # DATA batches (the unscheduled path)
    vm.run(6.0)
    arrivals: dict[int, list[tuple[int, int]]] = {}  # batch -> [(origin, tick)] in arrival order
    dec = StreamDecoder()
    own_waits = []
    for tick, chunk in vm.serial_chunks[1]:
        for f in dec.feed(chunk):
            if f.type is FrameType.DATA and not any(x.flags & SampleFlags.NO_MESH_TIME for x in payload_as(f, Data).samples):
                j = payload_as(f, Data).samples[0].index // 5
                arrivals.setdefault(j, []).append((f.origin, tick))
                if f.origin == 1:
                    last = vm.nodes[1].crystal.tick_at(payload_as(f, Data).samples[-1].cycle)
                    own_waits.append((tick - last) / CLOCK_HZ)
    whole = [a for j, a in sorted(arrivals.items()) if {o for o, _ in a} == {1, 2, 3, 4}][5:]
    assert len(whole) > 50
    assert all([o for o, _ in a] == [4, 3, 2, 1] for a in whole), whole[:3]
    # its own batch: the last sample's gates (2 + 2 ms), then its slot (slot_depths *
    # depth_slot, plus its offset of at most slot_jitter)
    from cellbridge.emulator.firmware.firmware import FirmwareConfig
    fc = FirmwareConfig(1)
    slot = fc.slot_depths * fc.depth_slot / CLOCK_HZ
    assert own_waits and all(slot + 0.004 <= w <= slot + 0.004 + fc.slot_jitter / CLOCK_HZ + 0.001
                             for w in own_waits[5:]), (slot, own_waits[:10])


def test_aligned_batches_put_one_group_of_indices_in_each_frame_on_every_bridge() -> None:
    # With aligned batches every bridge closes batch j (indices [5j, 5j + 5) at 100 Hz and
    # max_latency 50 ms) at the same global instant: no DATA frame mixes two batches.
    vm = VirtualMesh(meshgen.grid(3, 3, gateways=(1,)), seed=2, random_epochs=True, aligned_batches=True, readout=False)
    r = vm.run(6.0)
    groups = [{s.index // 5 for s in payload_as(f, Data).samples} for f in r.gateway_frames[1]
              if f.type is FrameType.DATA and not any(s.flags & SampleFlags.NO_MESH_TIME for s in payload_as(f, Data).samples)]
    assert len(groups) > 100
    assert all(len(g) == 1 for g in groups)


def test_a_relay_computes_its_readout_sample_at_its_childrens_records_not_at_a_wake_of_its_own() -> None:
    # On the readout schedule a relay's record goes when its children's records are in (or
    # at its slot): lazily, its own sample waits for the wake one of those records brings,
    # instead of waking the bridge at its gate end (a real-time process's wake costs more
    # than the sample). What leaves the gateway, and when, is exactly what gate-by-gate
    # sampling sends; the relays wake about once a frame less.
    mesh = meshgen.grid(3, 3, gateways=(1,))

    def run(lazy: bool) -> tuple[dict, dict, dict[int, int], int]:
        vm = VirtualMesh(mesh, seed=2, lazy_sampling=lazy, readout=True, readout_acks=False,
                         readout_window=READOUT_WINDOW, readout_hop=READOUT_HOP)

        wakes: dict[int, int] = dict.fromkeys(mesh.ids, 0)
        run_one = vm._run
        def counted(b: int) -> None:  # and counts each bridge's wakes after start-up
            if vm.tick >= 3.0 * CLOCK_HZ:
                wakes[b] += 1
            run_one(b)

        vm._run = counted  # type: ignore[method-assign]
        r = vm.run(4.0)
        records = [payload_as(f, Readout) for f in r.gateway_frames[1] if f.type is FrameType.READOUT]
        frames = sum(1 for x in records if x.index >= 3 * x.rate)
        return r.samples(), vm.serial_chunks, wakes, frames

    lazy_samples, lazy_frames, lazy_wakes, n = run(True)
    eager_samples, eager_frames, eager_wakes, _ = run(False)
    assert n >= 95  # the readout ran (a frame every 10 ms)
    assert lazy_samples == eager_samples
    assert lazy_frames == eager_frames
    vm = VirtualMesh(mesh, seed=2)
    vm.run(1.0)
    relays = {p for p in vm.result().parents.values() if p is not None} - set(mesh.gateways)
    assert relays
    for b in relays:  # a wake less per frame (100 in 1 s at 100 Hz)
        assert lazy_wakes[b] <= eager_wakes[b] - 95, (b, lazy_wakes[b], eager_wakes[b])
    for b in set(mesh.ids) - relays - set(mesh.gateways):  # a leaf's record goes at its gate end
        assert lazy_wakes[b] == eager_wakes[b]


def test_a_bridge_that_computes_its_next_samples_ahead_sends_what_it_sends_without() -> None:
    # The real-time shell has the chip compute the next samples' counts after a wake that
    # took one (Sampler.prefetch, process_bridge's PREFETCH): the same counts at the same
    # gates, whatever the mesh clock did meanwhile (a gate it moved is computed when it
    # is taken) and whatever the world did (a press: the pressed gates too). Same bytes at
    # the same ticks on the gateway's line, and most counts came from the prefetch.
    mesh = meshgen.grid(3, 3, gateways=(1,))
    presses = [Contact(2.6, 0.3, 0.04, 0.04, 2.0, 0.02)]

    def run(ahead: bool) -> tuple[dict, dict, int, int]:
        vm = VirtualMesh(mesh, seed=2, world=World(mesh, list(presses)), readout=True, readout_acks=False,
                         readout_window=READOUT_WINDOW, readout_hop=READOUT_HOP)

        if ahead:
            prefetch_after_sampling(vm)
        r = vm.run(3.5)
        hits = sum(fw.chip.prefetch_hits for fw in vm.nodes.values())  # type: ignore[attr-defined]
        return r.samples(), vm.serial_chunks, hits, r.total("samples")

    (a_samples, a_frames, hits, taken), (b_samples, b_frames, none, _) = run(True), run(False)
    assert a_samples == b_samples
    assert a_frames == b_frames
    # two counts a sample; the first ~2.5 s boot without mesh time, when nothing is computed ahead
    assert none == 0 and hits > taken // 2


def test_a_relay_whose_childs_record_comes_before_its_own_gate_end_sends_at_its_gate_end() -> None:
    # A child with a shorter gate (SET_GATE to that bridge alone) ends its gate, and its
    # record reaches the relay, before the relay's own gate ends. The wake that record
    # brought came before the relay's sample could be taken: lazily the relay must still
    # take it at its gate end, as gate by gate, not at the next wake that happens to come
    # (the frame's wait for a record of its own, a window later: every frame of the
    # relay's subtree reached the gateway 7 ms later than gate by gate).
    mesh = meshgen.grid(3, 3, gateways=(1,))
    probe = VirtualMesh(mesh, seed=2)
    probe.run(1.0)
    parents = probe.result().parents
    relays = {p for p in parents.values() if p is not None} - set(mesh.gateways)
    leaves = sorted(set(mesh.ids) - relays - set(mesh.gateways))
    assert relays and leaves

    def run(lazy: bool) -> tuple[list, list]:
        vm = VirtualMesh(mesh, seed=2, lazy_sampling=lazy, readout=True, readout_acks=False,
                         readout_window=READOUT_WINDOW, readout_hop=READOUT_HOP)
        for i, b in enumerate(leaves):  # a fifth of the relays' gates
            vm.host_write(1, cmd(100 + i, b, Op.SET_GATE, 20_000, token=100 + i), at=2.8)
        r = vm.run(3.6)
        got = [f for f in r.gateway_frames[1] if f.type is FrameType.CMD_REPLY]
        assert len(got) == len(leaves) and all(f.payload.status is Status.OK for f in got)  # type: ignore[union-attr]  # CMD_REPLY payloads
        return vm.serial_chunks[1], r.gateway_frames[1]

    (lazy, frames), (eager, _) = run(True), run(False)
    records = [payload_as(f, Readout) for f in frames if f.type is FrameType.READOUT]
    assert sum(1 for x in records if x.index >= 3 * x.rate) >= 50
    assert lazy == eager


def test_a_contact_the_world_takes_back_still_pressed_the_gates_before() -> None:
    # A bridge process mirrors the world process's list of contacts, and computes samples
    # after their gates (a relay's readout sample at its children's records). A list that
    # no longer holds a press that was on (a world that restarted) takes over when the
    # bridge hears it: a gate before then still sensed the press, one after does not.
    mesh = meshgen.grid(3, 3, gateways=(1,))
    world = World(mesh)
    on = Contact(1.0, math.inf, 0.04, 0.04, 3.0, 0.02)
    world.set_contacts([on], 1.0)
    sense = world.sense_for(5)
    pressed, rest = sense(int(1.5 * CLOCK_HZ)), world.rest
    assert pressed != rest
    world.set_contacts([], 2.0)
    assert sense(int(1.99 * CLOCK_HZ)) == pressed  # a gate before the new list: pressed
    assert sense(int(2.0 * CLOCK_HZ)) == rest
    later = Contact(2.5, 1.0, 0.04, 0.04, 3.0, 0.02)
    world.set_contacts([later], 3.0)  # heard late: it pressed from its own start
    assert sense(int(2.6 * CLOCK_HZ)) == pressed and sense(int(1.99 * CLOCK_HZ)) == pressed
    world.set_contacts([later], 4.5)  # the same list again: nothing changes
    assert sense(int(1.99 * CLOCK_HZ)) == pressed
    world.set_contacts([], 4.5)  # the first press ended at 2.0, over 2 s ago: forgotten
    assert sense(int(1.99 * CLOCK_HZ)) == rest and sense(int(2.6 * CLOCK_HZ)) == pressed


def test_a_relays_lazy_sample_sees_a_press_the_world_took_back_after_its_gate() -> None:
    # The contact list a bridge process mirrors changes between a relay's gate and the
    # wake that computes its readout sample lazily (its children's records): a list
    # without a press that was on at the gate. Lazily the relay must send what gate by
    # gate sampling sends (the press at that gate), the same bytes at the same ticks.
    mesh = meshgen.grid(3, 3, gateways=(1,))

    def run(lazy: bool) -> list[tuple[int, bytes]]:
        world = World(mesh)
        vm = VirtualMesh(mesh, seed=2, world=world, lazy_sampling=lazy, readout=True, readout_acks=False,
                         readout_window=READOUT_WINDOW, readout_hop=READOUT_HOP)
        world.set_contacts([Contact(3.0, math.inf, 0.04, 0.04, 3.0, 0.2)], 0.0)

        def publish(contacts: list[Contact], t: float) -> Callable[[], None]:
            return lambda: world.set_contacts(contacts, t)

        for t in (3.104, 3.2041, 3.3047):  # just after the leaves' gate ends (3.1039 ...)
            vm.at(t, publish([], t))
            vm.at(t + 0.05, publish([Contact(t + 0.05, math.inf, 0.04, 0.04, 3.0, 0.2)], t + 0.05))
        vm.run(3.5)
        return vm.serial_chunks[1]

    assert run(True) == run(False)


def test_a_lossy_skin_with_two_gateways_sends_the_same_lazily_and_gate_by_gate() -> None:
    # Booting on lossy cells, relays hold frames besides their records (DATA of samples
    # from before mesh time, HELLO, STATUS): lazily a relay wakes only for its children's
    # records, and a frame queued behind a record must still go when it would gate by
    # gate (it went up to 180 ms later, behind 18 records).
    mesh = meshgen.grid(3, 3, gateways=(1, 9), loss=0.03)

    def run(lazy: bool) -> list[list[tuple[int, bytes]]]:
        vm = VirtualMesh(mesh, seed=2, lazy_sampling=lazy, readout=True, readout_acks=False,
                         readout_window=READOUT_WINDOW, readout_hop=READOUT_HOP)
        vm.run(2.8)
        return [vm.serial_chunks[g] for g in mesh.gateways]

    assert run(True) == run(False)

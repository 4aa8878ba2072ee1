"""Mesh files: generators, round trip, and refusal of bad files with the key named."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import MeshError, mesh_to_toml, parse_mesh
from cellbridge.protocol import Data
from hypothesis import given, settings
from hypothesis import strategies as st

from support.payloads import payload_as

CLI = shutil.which("cellbridge", path=str(Path(sys.executable).parent)) or "cellbridge"

GOOD = """
[[cell]]
id = 1
[[cell]]
id = 2
[[bridge]]
id = 1
cells = [1]
position = [0.0, 0.0]
gateway = true
[[bridge]]
id = 2
cells = [1, 2]
position = [0.04, 0.0]
[[bridge]]
id = 3
cells = [2]
position = [0.08, 0.0]
"""


def test_good_file_parses() -> None:
    m = parse_mesh(GOOD)
    assert m.ids == [1, 2, 3] and m.gateways == [1]
    assert m.neighbours() == {1: [2], 2: [1, 3], 3: [2]}


@pytest.mark.parametrize("edit, words", [
    (lambda t: t + "\nbogus = 1\n", ["unknown key 'bogus'"]),
    (lambda t: t.replace("position = [0.08, 0.0]", "position = [0.08, 0.0]\ncolour = 1"), ["bridge[2]", "colour"]),
    (lambda t: t.replace("id = 3\ncells = [2]", "id = 2\ncells = [2]"), ["duplicate bridge id 2"]),
    (lambda t: t.replace("[[cell]]\nid = 2", "[[cell]]\nid = 1"), ["duplicate cell id 1"]),
    (lambda t: t.replace("cells = [2]\n", "cells = []\n"), ["bridge 3 is on no cell"]),
    (lambda t: t.replace("cells = [1, 2]", "cells = [1]"), ["bridge 3 is unreachable"]),
    (lambda t: t.replace("cells = [2]\n", "cells = [9]\n"), ["cell 9 is not declared"]),
    (lambda t: t + "\n[[link]]\na = 1\nb = 7\nloss = 0.1\n", ["link[0].b", "missing bridge 7"]),
    (lambda t: t.replace("gateway = true", ""), ["no bridge has 'gateway = true'"]),
    (lambda t: t.replace("position = [0.04, 0.0]", "position = [0.02, 0.0]"), ["overlaps"]),
    (lambda t: "loss = 2.0\n" + t, ["loss", "probability"]),
    (lambda t: t.replace("id = 3\ncells", "cells"), ["bridge[2]", "missing key 'id'"]),
    (lambda t: t + "\n[[bridge]\n", ["not valid TOML"]),
    # issue 17, point 19: every bridge crashed on a side its element model refuses
    (lambda t: "side = 2.0\n" + t, ["side", "1"]),
    # ... a = true is bridge 1 to Python (True == 1); a repeated pair's loss was ignored
    (lambda t: t + "\n[[link]]\na = true\nb = 2\n", ["link[0].a", "integer"]),
    (lambda t: t + "\n[[link]]\na = 1\nb = 2\nloss = 0.1\n[[link]]\na = 2\nb = 1\nloss = 0.5\n",
     ["link[1]", "1-2", "link[0]"]),
    # point 18: the second gateway died on the port the first had bound
    (lambda t: t.replace("gateway = true", "gateway = true\ntcp = 6000").replace(
        "position = [0.08, 0.0]", "position = [0.08, 0.0]\ngateway = true\ntcp = 6000"),
     ["bridge[2]", "tcp", "6000", "bridge 1"]),
])
def test_bad_files_are_refused_naming_the_problem(edit, words) -> None:
    with pytest.raises(MeshError) as exc:
        parse_mesh(edit(GOOD), "skin.toml")
    msg = str(exc.value)
    assert msg.startswith("skin.toml")
    for w in words:
        assert w in msg


@pytest.mark.parametrize("mesh, n, hops", [
    (meshgen.line(8), 8, 7),
    (meshgen.ring(10), 10, 5),
    (meshgen.grid(4, 4, gateways=(1,)), 16, 6),
    (meshgen.random_mesh(32, seed=5), 32, None),
])
def test_generators_make_valid_connected_meshes(mesh, n, hops) -> None:
    assert len(mesh.bridges) == n
    assert mesh.reachable() == set(mesh.ids)
    assert parse_mesh(mesh_to_toml(mesh)) == mesh
    if hops is not None:  # breadth-first depth from the gateway
        nb, depth, todo = mesh.neighbours(), {1: 0}, [1]
        for b in todo:
            for x in nb[b]:
                if x not in depth:
                    depth[x] = depth[b] + 1
                    todo.append(x)
        assert max(depth.values()) == hops


def test_random_mesh_has_shared_cells() -> None:
    m = meshgen.random_mesh(32, seed=1)
    assert max(len(v) for v in m.members().values()) >= 3


@settings(max_examples=25, deadline=None)
@given(st.integers(2, 40), st.integers(0, 10_000))
def test_random_meshes_round_trip_and_are_connected(n: int, seed: int) -> None:
    m = meshgen.random_mesh(n, seed=seed)
    assert m.reachable() == set(m.ids)
    assert parse_mesh(mesh_to_toml(m)) == m


def test_cut_cells_and_dead_bridges_change_reachability() -> None:
    m = meshgen.line(5)
    assert m.reachable(dead=frozenset({3})) == {1, 2}
    assert m.reachable(cut=frozenset({1})) == {1}
    r = meshgen.ring(6)
    assert r.reachable(dead=frozenset({2})) == {1, 3, 4, 5, 6}


@given(st.integers(1, 8), st.integers(1, 8))
@settings(max_examples=25, deadline=None)
def test_a_grids_default_gateway_is_its_centre_the_shallowest_tree(rows: int, cols: int) -> None:
    """A frame's readout climbs the routing tree hop by hop: a generated grid's one gateway
    is the bridge no other bridge of the grid is further from than from any other."""
    mesh = meshgen.grid(rows, cols)
    [gw] = mesh.gateways
    assert gw == meshgen.grid_centre(rows, cols)

    def deepest(g: int) -> int:
        return max(meshgen.grid(rows, cols, gateways=(g,)).hops().values())

    assert deepest(gw) == min(deepest(b) for b in mesh.ids)


def test_cli_gen_puts_a_grids_gateway_at_its_centre_and_other_kinds_at_bridge_1(tmp_path: Path) -> None:
    for args, want in ((["grid", "4", "4"], [6]), (["grid", "8", "8"], [28]), (["grid", "2", "2"], [1]),
                       (["line", "8"], [1]), (["ring", "6"], [1])):
        r = subprocess.run([CLI, "mesh", "gen", *args], capture_output=True, timeout=60)
        assert r.returncode == 0, r.stderr
        assert parse_mesh(r.stdout.decode()).gateways == want, args


def test_cli_gen_and_check(tmp_path: Path) -> None:
    out = tmp_path / "g.toml"
    r = subprocess.run([CLI, "mesh", "gen", "grid", "2", "3", "--gateways", "1,6", "-o", str(out)],
                       capture_output=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert parse_mesh(out.read_text()).gateways == [1, 6]
    r = subprocess.run([CLI, "mesh", "check", str(out)], capture_output=True, timeout=60)
    assert r.returncode == 0 and b"6 bridges" in r.stdout
    bad = tmp_path / "bad.toml"
    bad.write_text(GOOD.replace("cells = [2]\n", "cells = []\n"))
    r = subprocess.run([CLI, "mesh", "check", str(bad)], capture_output=True, timeout=60)
    assert r.returncode == 2 and b"bridge 3 is on no cell" in r.stderr and b"Traceback" not in r.stderr
    r = subprocess.run([CLI, "mesh", "gen", "line", "4", "--gateways", "9"], capture_output=True, timeout=60)
    assert r.returncode == 2 and b"gateway 9" in r.stderr


def test_cli_gen_refuses_a_seed_for_a_shape_it_cannot_change() -> None:
    """`mesh gen grid 4 4 --seed 7` took the seed and wrote the one grid there is, as if it
    had mattered (the help says: random mesh only). It is refused; a random mesh takes it."""
    r = subprocess.run([CLI, "mesh", "gen", "grid", "2", "2", "--seed", "7"], capture_output=True, timeout=60)
    assert r.returncode == 2 and not r.stdout and b"--seed shapes a random mesh only, not a grid" in r.stderr
    seeded = [subprocess.run([CLI, "mesh", "gen", "random", "6", "--seed", s], capture_output=True, timeout=60)
              for s in ("0", "7")]
    assert all(r.returncode == 0 for r in seeded) and seeded[0].stdout != seeded[1].stdout


def test_cli_gen_and_run_say_which_file_they_cannot_write(tmp_path: Path) -> None:
    """`mesh gen -o` into a folder that does not exist, and `mesh run --capture` naming a
    file, printed a Python traceback: a sentence naming the path now, before any run."""
    mesh = tmp_path / "line.toml"
    mesh.write_text(mesh_to_toml(meshgen.line(2)))
    for args, path in ((["gen", "line", "3", "-o", str(tmp_path / "no" / "x.toml")], tmp_path / "no" / "x.toml"),
                       (["run", str(mesh), "--seconds", "0.1", "--capture", str(mesh)], mesh)):
        r = subprocess.run([CLI, "mesh", *args], capture_output=True, timeout=60)
        assert r.returncode == 2 and b"Traceback" not in r.stderr, r.stderr
        assert f"{path}: cannot write".encode() in r.stderr and not r.stdout


def test_cli_run_in_virtual_time_with_scenario_and_capture(tmp_path: Path) -> None:
    import json

    from cellbridge.protocol import FrameType, StreamDecoder

    mesh = tmp_path / "line.toml"
    mesh.write_text(mesh_to_toml(meshgen.line(3)))
    scenario = tmp_path / "press.toml"
    scenario.write_text("[[contact]]\nstart = 0.5\nduration = 0.4\nposition = [0.08, 0.0]\n"
                        "force = 3.0\ndiameter = 0.02\n")
    out = tmp_path / "cap"
    r = subprocess.run([CLI, "mesh", "run", str(mesh), "--seconds", "1.5", "--scenario", str(scenario),
                        "--capture", str(out)], capture_output=True, timeout=120)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert all(n > 100 for n in summary["samples_delivered"].values())
    frames = StreamDecoder().feed((out / "gateway-1.bin").read_bytes())
    c1 = {s.cycle: s.c1 for f in frames if f.type is FrameType.DATA and f.origin == 3 for s in payload_as(f, Data).samples}
    pressed = [v for cyc, v in c1.items() if 0.55e0 * 50e6 <= cyc < 0.85 * 50e6]
    idle = [v for cyc, v in c1.items() if cyc < 0.45 * 50e6]
    assert pressed and idle and max(pressed) < min(idle) - 100  # the press raised C1 of bridge 3
    bad = tmp_path / "bad.toml"
    bad.write_text("[[contact]]\nstart = 0\n")
    r = subprocess.run([CLI, "mesh", "run", str(mesh), "--scenario", str(bad)], capture_output=True, timeout=60)
    assert r.returncode == 2 and b"missing key" in r.stderr


@given(st.text(max_size=40))
@settings(max_examples=200, deadline=None)
def test_any_mesh_name_round_trips_through_toml(name: str) -> None:
    # a user's name with quotes, backslashes, newlines or control characters must not
    # make mesh_to_toml write a file that no longer parses (or parses to another name)
    from dataclasses import replace

    mesh = replace(meshgen.line(2), name=name, _by_id={})
    assert parse_mesh(mesh_to_toml(mesh)).name == name


def test_sampling_rates_the_gates_cannot_hold_are_refused(tmp_path: Path) -> None:
    # --rate 0 crashed every process with a traceback; --rate 1000 (four times the gate
    # limit) ran with overlapping gates, a schedule no chip can keep.
    from cellbridge.emulator.firmware.commands import Settings
    from cellbridge.emulator.mesh.virtual import VirtualMesh

    for rate in (0, -5, 251, 1000):
        with pytest.raises(ValueError, match=f"sampling rate {rate} Hz: must be 1..250 Hz"):
            VirtualMesh(meshgen.line(2), settings=Settings(rate_hz=rate))
    path = tmp_path / "l2.toml"
    path.write_text(mesh_to_toml(meshgen.line(2)))
    for args, words in [(["mesh", "run", str(path), "--rate", "0"], b"sampling rate 0 Hz"),
                        (["mesh", "run", str(path), "--rate", "1000"], b"must be 1..250 Hz"),
                        (["mesh", "run", str(path), "--seconds", "nan"], b"--seconds"),
                        (["mesh", "run", str(path), "--seconds", "-1"], b"--seconds"),
                        (["mesh", "up", str(path), "--rate", "1000"], b"must be 1..250 Hz"),
                        (["bridge", "--mesh", str(path), "--id", "2", "--rate", "0"], b"sampling rate 0 Hz")]:
        r = subprocess.run([CLI, *args], capture_output=True, timeout=60)
        assert r.returncode == 2 and words in r.stderr and b"Traceback" not in r.stderr, (args, r.stderr)


def test_cli_run_refuses_a_scenario_contact_beside_the_skin(tmp_path: Path) -> None:
    path = tmp_path / "l2.toml"
    path.write_text(mesh_to_toml(meshgen.line(2)))
    scenario = tmp_path / "s.toml"
    scenario.write_text("[[contact]]\nstart = 0.1\nduration = 0.2\nposition = [40.0, 0.0]\n"
                        "force = 2.0\ndiameter = 0.02\n")
    r = subprocess.run([CLI, "mesh", "run", str(path), "--seconds", "0.5", "--scenario", str(scenario)],
                       capture_output=True, timeout=60)
    assert r.returncode == 2 and b"contact[0]" in r.stderr and b"touches no element" in r.stderr, r.stderr


def test_next_event_names_the_tick_the_mesh_next_acts_at() -> None:
    """A caller pacing the mesh to a clock sleeps until ``next_event``: nothing may be due
    before it (a later tick named would run events late), and running to it runs what
    was due then (an earlier tick named would wake the caller for nothing, for ever)."""
    from cellbridge.emulator.mesh.virtual import CLOCK_HZ, VirtualMesh

    vm = VirtualMesh(meshgen.grid(2, 2), seed=1)
    vm.run(0.3)
    waited = 0
    for _ in range(300):
        t = vm.next_event()
        assert t is not None and t >= vm.tick
        if t - vm.tick >= 2:
            vm.run((t - vm.tick - 0.5) / CLOCK_HZ)  # to the tick before it
            assert vm.next_event() == t  # nothing ran
            waited += 1
        vm.run((t - vm.tick + 0.5) / CLOCK_HZ)  # to it
        after = vm.next_event()
        assert after is None or after > t  # what was due at t ran (and planned only later)
    assert waited > 100  # events apart, not one tick after another


def test_advance_to_refuses_a_tick_before_now() -> None:
    """Virtual time never runs backwards: a mesh set back would stamp what it sends next
    earlier than what it already sent, and its result would report an elapsed time it
    has passed."""
    from cellbridge.emulator.mesh.virtual import VirtualMesh

    vm = VirtualMesh(meshgen.grid(2, 2), seed=1)
    vm.run(0.3)
    now = vm.tick
    with pytest.raises(ValueError, match="before"):
        vm.advance_to(now - 1)
    with pytest.raises(ValueError, match="before"):
        vm.run(-0.01)
    assert vm.tick == now
    vm.advance_to(now)  # (now itself: nothing to do, allowed)
    assert vm.tick == now


def test_an_action_planned_for_a_time_passed_runs_now() -> None:
    """A fault or command planned at a virtual time the mesh has already passed (a
    scenario that schedules between run() or advance_to() calls) runs at the current
    tick: run at its own, it would stamp the gateway's output before what was already
    sent (a replay of the line would then go back in time), and ``next_event`` would
    name a tick in the past to a caller pacing the mesh to a clock."""
    from cellbridge.emulator.mesh.virtual import VirtualMesh
    from cellbridge.protocol import Command, Flags, Frame, Op

    vm = VirtualMesh(meshgen.line(3), seed=1)
    vm.run(0.5)
    now = vm.tick
    seen: list[int] = []
    vm.at(0.1, lambda: seen.append(vm.tick))
    vm.host_write(1, Frame(0, 1, 0, 7, Command(9, Op.PING, None), flags=int(Flags.ACK_REQUEST)), at=0.1)
    t = vm.next_event()
    assert t is not None and t >= now
    vm.run(0.2)
    assert seen == [now]
    stamps = [tick for tick, _ in vm.serial_chunks[1]]
    assert stamps == sorted(stamps) and stamps[-1] >= now

"""The readout's share of a cell's airtime, estimated from a mesh alone: it agrees with
what the virtual-time mesh does, and `mesh check`, `mesh run` say when it does not fit."""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import Bridge, Cell, Mesh, mesh_to_toml
from cellbridge.emulator.mesh.readout_load import FITS_BELOW, ack_bits, readout_load, record_frames, records_frames
from cellbridge.emulator.mesh.virtual import VirtualMesh
from cellbridge.protocol import Readout, StreamDecoder
from cellbridge.protocol.messages import pack_payload

CLI = shutil.which("cellbridge", path=str(Path(sys.executable).parent)) or "cellbridge"


def star(n: int) -> Mesh:
    """A gateway and ``n`` bridges on one cell."""
    return Mesh((Cell(1),), tuple(Bridge(i, (1,), ((i - 1) * 0.04, 0.0), i == 1) for i in range(1, n + 2)),
                name=f"star-{n}")


def states(vm: VirtualMesh, gateway: int, first: int) -> Counter[str]:
    """Samples, unchanged and missing entries in the gateway's records of frames >= ``first``."""
    dec = StreamDecoder()
    out: Counter[str] = Counter()
    for _, chunk in vm.serial_chunks[gateway]:
        for f in dec.feed(chunk):
            if isinstance(f.payload, Readout) and f.payload.index >= first:
                out.update(s=len(f.payload.samples), m=len(f.payload.missing))
    return out


def test_a_record_costs_its_parts_and_a_larger_one_more() -> None:
    one, parts1 = record_frames(1, 100)
    big, parts64 = record_frames(64, 100)
    assert parts1 == 1 and parts64 > 1  # 64 samples do not fit one frame
    assert big - one >= 63 * 8 * 10  # every sample's bytes (10 at least) are on the air
    assert ack_bits() > 0


def test_the_load_grows_with_the_rate_and_the_bridges_on_a_cell() -> None:
    a, b = readout_load(star(4), 100), readout_load(star(4), 250)
    assert b.peak == pytest.approx(2.5 * a.peak, rel=0.02)  # about the same bits a frame, 2.5 frames as often
    assert readout_load(star(8), 100).peak == pytest.approx(2 * a.peak)  # one-sample records each
    assert readout_load(star(4), 100, acked=False).peak < a.peak
    assert a.busiest == 1 and not a.unreached


def test_a_relay_carries_its_subtree_on_all_its_cells() -> None:
    line = meshgen.line(4)  # gateway 1 -[cell 1]- 2 -[cell 2]- 3 -[cell 3]- 4
    assert line.members() == {1: [1, 2], 2: [2, 3], 3: [3, 4]}
    load = readout_load(line, 100).load
    period = line.bitrate / 100
    rec = {n: record_frames(n, 100)[0] for n in (1, 2, 3)}
    # cell 1: bridge 2's record of its subtree (3 samples), bridge 1's acknowledgement of
    # it and bridge 2's of bridge 3's record (a radio sends on all its cells)
    assert load[1] * period == pytest.approx(rec[3] + 2 * ack_bits())
    # cell 2: the records of bridges 2 (3 samples) and 3 (2), and the acknowledgements of 2 and 3
    assert load[2] * period == pytest.approx(rec[3] + rec[2] + 2 * ack_bits())
    assert load[3] * period == pytest.approx(rec[2] + rec[1] + ack_bits())


@pytest.mark.parametrize("n, rate, fits", [(4, 250, True), (8, 250, False)])
def test_the_verdict_is_what_the_virtual_mesh_does(n: int, rate: int, fits: bool) -> None:
    """A star whose cell the model says carries its readout loses no element-frame in
    virtual time; one it says does not lists a large share of them missing."""
    mesh = star(n)
    assert readout_load(mesh, rate).fits is fits
    vm = VirtualMesh(mesh, seed=1, settings=Settings(rate_hz=rate), readout=True)
    vm.run(4.0)
    got = states(vm, 1, int(3.0 * rate))
    assert got["s"] > 0
    share = got["m"] / (got["s"] + got["m"])
    if fits:
        assert share == 0, got
    else:
        assert share > 0.05, got


def test_the_default_grids_fit_at_the_default_rate() -> None:
    for mesh in (meshgen.grid(4, 4), meshgen.grid(8, 8)):
        assert readout_load(mesh, 100).fits, mesh.name
    assert not readout_load(meshgen.grid(8, 8, gateways=(1,)), 250).fits


def test_check_and_run_say_when_it_does_not_fit(tmp_path: Path) -> None:
    crowded = tmp_path / "star.toml"
    crowded.write_text(mesh_to_toml(star(8)))
    r = subprocess.run([CLI, "mesh", "check", str(crowded), "--rate", "250"], capture_output=True, timeout=60)
    assert r.returncode == 0, r.stderr  # the file is valid
    assert b"the busiest cell, 1," in r.stdout and b"warning: at 250 Hz" in r.stderr
    r = subprocess.run([CLI, "mesh", "check", str(crowded), "--rate", "50"], capture_output=True, timeout=60)
    assert r.returncode == 0 and b"warning" not in r.stderr
    line = f"{FITS_BELOW * 100:.0f}%".encode()
    assert line in r.stdout
    r = subprocess.run([CLI, "mesh", "run", str(crowded), "--rate", "250", "--seconds", "0.05"], capture_output=True,
                       timeout=120)
    assert r.returncode == 0 and b"warning: at 250 Hz" in r.stderr


def test_records_of_every_size_cost_what_each_split_alone_does() -> None:
    # readout_load prices all its subtrees' records at once (records_frames): the same bits
    # and parts as splitting each record by itself (record_frames, the firmware's _split)
    sizes = set(range(1, 160)) | {300, 777}
    table = records_frames(sizes, 100)
    assert table == {n: record_frames(n, 100) for n in sizes}
    assert records_frames({5, 40}, 250) == {5: record_frames(5, 250), 40: record_frames(40, 250)}


def test_a_long_line_is_priced_without_packing_its_records_again_and_again(monkeypatch: pytest.MonkeyPatch) -> None:
    # Each of a line's subtrees is of another size, and splitting each record whole packed
    # its samples over and over (a line of 1000 bridges: a minute before mesh check said
    # anything). Counted here as the samples packed into payloads: about each once.
    from cellbridge.emulator.firmware import readout as readout_module
    from cellbridge.emulator.mesh import readout_load as load_module

    packed = [0]

    def counting(payload: object) -> bytes:
        packed[0] += len(getattr(payload, "samples", ()))
        return pack_payload(payload)  # type: ignore[arg-type]

    monkeypatch.setattr(readout_module, "pack_payload", counting)
    monkeypatch.setattr(load_module, "pack_payload", counting)
    line = meshgen.line(300)
    load = readout_load(line, 100)
    assert load.busiest == 2 and not load.fits
    assert packed[0] < 20 * len(line.bridges)


def test_a_mesh_of_gateways_alone_says_no_cell_carries_a_record() -> None:
    from cellbridge.emulator.mesh.readout_load import load_line

    alone = Mesh((Cell(1),), (Bridge(1, (1,), (0.0, 0.0), True),), name="alone")
    load = readout_load(alone, 100)
    assert load.peak == 0 and load.fits
    assert load_line(load) == "readout at 100 Hz: no cell carries a record"

"""The humanoid's skin (cellbridge/skins/humanoid.toml): it loads, every element is placed
in its link's frame, and its frame-level traffic read by the daemon's core gives the
contacts at the links pressed, and nowhere else."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cellbridge.daemon.shell.skin_file import load_skin
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.mesh.skin_mesh import mesh_from_skin
from cellbridge.emulator.mesh.skin_traffic import SkinTraffic, readout_tree
from cellbridge.emulator.realtime.realtime import reporting_arg
from cellbridge.emulator.world.world import Contact, World
from cellbridge.protocol import Readout, StreamDecoder

from cellbridge.skin_run import run_daemon_on_traffic
from support.payloads import payload_as

HUMANOID = Path(__file__).resolve().parents[1] / "cellbridge" / "skins" / "humanoid.toml"
PRESSED = (("forearm_left", 3, 2), ("thigh_right", 5, 5), ("chest", 6, 3), ("head", 2, 9))


@pytest.fixture(scope="module")
def skin():
    return load_skin(HUMANOID)


def test_the_humanoid_loads_with_every_element_placed_in_its_link_frame(skin) -> None:
    assert skin.n >= 1100
    assert len(skin.gateways) >= 8
    assert skin.position.shape == (skin.n, 3) and skin.normal.shape == (skin.n, 3)
    assert np.isfinite(skin.position).all()
    assert np.allclose(np.linalg.norm(skin.normal, axis=1), 1.0)
    links = {ln.name for ln in skin.links}
    assert {p.link for p in skin.patches} <= links and len(links) >= 11
    for p in skin.patches:  # a cylinder's normal points away from its axis, a plane's along its frame's z
        rows = np.array([skin.row_of(skin.element_id(p.name, r, c)) for r in range(p.rows) for c in range(p.cols)])
        pose = np.asarray(p.pose)
        local = (skin.position[rows] - pose[:3, 3]) @ pose[:3, :3]
        n_local = skin.normal[rows] @ pose[:3, :3]
        if p.shape == "cylinder":
            assert np.allclose(np.hypot(local[:, 0], local[:, 1]), p.radius)
            assert np.allclose(n_local[:, :2], local[:, :2] / p.radius) and np.allclose(n_local[:, 2], 0.0)
        else:
            assert np.allclose(local[:, 2], 0.0) and np.allclose(n_local, [0.0, 0.0, 1.0])
    tree = readout_tree(skin)  # every element reaches a gateway of its own surface
    assert (tree.depth >= 0).all() and np.bincount(tree.gateway).max() <= 65


def test_frame_level_traffic_is_the_firmware_s_readout_records(skin) -> None:
    traffic = SkinTraffic(skin)
    reads = traffic.frame(7)
    assert sorted(g for _, g, _ in reads) == sorted(skin.gateway_ids())
    seen: list[int] = []
    for t, g, data in reads:
        frames = StreamDecoder().feed(data)
        assert frames and all(f.origin == g for f in frames)
        recs = [payload_as(f, Readout) for f in frames]
        assert all(f.src == g for f in frames)
        assert [r.part for r in recs] == list(range(recs[0].parts))
        assert all(r.index == 7 and r.rate == 100 and not r.missing and not r.unchanged for r in recs)
        seen += [s.bridge for r in recs for s in r.samples]
        assert 0.07 + 0.004 < t <= 0.07 + recs[0].span_us * 1e-6  # after the gates, by the gateway's slot
    assert sorted(seen) == sorted(skin.ids.tolist())  # every element once


@pytest.mark.parametrize("reporting", ["periodic", "event:30"])
def test_presses_on_the_humanoid_give_contacts_at_the_pressed_links(skin, reporting: str) -> None:
    presses = []
    for patch, row, col in PRESSED:
        x, y = skin.atlas[skin.row_of(skin.element_id(patch, row, col))]
        presses.append(Contact(0.8, 0.8, x + 0.01, y - 0.005, 3.0, 0.02))
    traffic = SkinTraffic(skin, World(mesh_from_skin(skin), presses),
                          settings=Settings(reporting=reporting_arg(reporting)))
    during: dict[tuple[str, str], list[dict]] = {}
    for t, topic, m in run_daemon_on_traffic(traffic, 1.8):
        if topic != "contact":
            continue
        for c in m["contacts"]:
            if c["missed"] == 0:
                assert 0.8 < t < 1.8, f"a contact at {t:.3f} s, outside the presses"
                during.setdefault((c["link"], c["patch"]), []).append(c)
    want = {(skin.patch(p).link, p) for p, _, _ in PRESSED}
    assert set(during) == want
    for (_link, patch), cs in during.items():
        (p, r, c) = next(q for q in PRESSED if q[0] == patch)
        element = skin.element_id(p, r, c)
        mid = cs[len(cs) // 2]
        assert element in mid["elements"]
        assert mid["force"] == pytest.approx(3.0, rel=0.1)
        # 1 cm along the atlas x and 5 mm back along y from the element's centre, on its link
        assert np.linalg.norm(np.asarray(mid["position"]) - skin.position[skin.row_of(element)]) < 0.02
        assert len(cs) > 40  # published frame after frame while pressed


def test_mesh_traffic_writes_captures_the_daemon_replays(tmp_path) -> None:
    import json
    import subprocess
    import sys

    from cellbridge.daemon.shell.replay_source import read_records

    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "cellbridge", "mesh", "traffic", str(HUMANOID), "--seconds", "0.2",
                           "--reporting", "event:30", "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["elements"] == 1144 and summary["gateways"] == 22 and summary["records"] == 20 * 22
    caps = sorted(out.glob("gateway-*.cbcap"))
    assert len(caps) == 22
    reads = list(read_records(caps[0], "x"))
    assert len(reads) == 21 and reads[0][1] == b"" and all(b >= a for (a, _), (b, _) in zip(reads, reads[1:]))
    # every line starts at one instant (an empty read): replayed, each shifted to its own start,
    # the gateways' records of a frame stay as far apart as they came
    assert len({next(iter(read_records(c, "x")))[0] for c in caps}) == 1
    check = subprocess.run([sys.executable, "-m", "cellbridge", "daemon", "--config", str(out / "daemon.toml"),
                            "--check"], capture_output=True, text=True, timeout=120)
    assert check.returncode == 0 and "22 link(s)" in check.stdout + check.stderr
    bad = subprocess.run([sys.executable, "-m", "cellbridge", "mesh", "traffic", str(tmp_path / "none.toml"),
                          "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "none.toml" in bad.stderr

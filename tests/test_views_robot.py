"""The views of a skin on a robot (bench/robot_payloads.py: the arm's topology and contacts as
the daemon makes them), as real processes fed by a stand-in daemon over loopback ZeroMQ:

- ``cellbridge foxglove`` to a client of the Foxglove protocol that decodes the advertised
  schemas: ``foxglove.FrameTransforms`` (each link in its parent's frame, as the skin
  description poses it), ``foxglove.SceneUpdate`` of the patches (a tile per element at its
  centre in its link's frame, facing along its normal) and of the contacts (in their
  link's frame, an arrow along the force vector whose head touches the skin);
- ``cellbridge web`` in chromium and ``cellbridge watch`` in a pty: the skin patch by
  patch, each patch's link and name above its block, the pressed elements in the colour
  of their force, the contacts on their patch.

With ``CELLBRIDGE_PICTURES=DIR`` the page of the whole-robot demo (a press of the arm's
``cellbridge robot run`` scenario, as its daemon published it) is written to
DIR/web-robot.png.
"""

from __future__ import annotations

import math
import os
import struct
import time
from pathlib import Path
from typing import Any

import pytest

import robot_payloads as rp
from browser import CHROMIUM, browser
from cellbridge.views.model import level_rgb
from cellbridge.views.robot_skin import rotate
from fake_daemon import FakeDaemon
from pty_terminal import pty_program
from support.view_clients import args, picture, pixel, server_view
from view_harness import CLI

needs_chromium = pytest.mark.skipif(CHROMIUM is None,
                                    reason="Debian's chromium is not installed (make test installs it with apt-get as root)")


def feed(fd: FakeDaemon, sk: Any, seq: int) -> None:
    fd.publish("topology", rp.topology(sk, seq))
    fd.publish("element", rp.element(sk, seq))
    fd.publish("contact", rp.contact(sk, seq))
    fd.publish("health", {"v": 2, "seq": seq, "source": rp.SOURCE, "uptime": float(seq),
                          "links": {"gw": {"connected": True}}})


def near(a: Any, b: Any, tol: float = 1e-6) -> bool:
    return all(abs(x - y) <= tol for x, y in zip(a, b))


def xyz(v: Any) -> tuple[float, float, float]:
    return (v.x, v.y, v.z)


def quat(q: Any) -> tuple[float, float, float, float]:
    return (q.x, q.y, q.z, q.w)


def test_foxglove_draws_the_patches_on_their_links_and_each_contact_as_an_arrow_along_its_force() -> None:
    from cellbridge.views.foxglove import TOPICS
    from foxglove_client import FoxgloveClient

    sk = rp.skin()
    topo = rp.topology(sk)["skin"]
    published = rp.contacts(sk)
    with FakeDaemon(layout=rp.layout(sk), reply=rp.reply(sk)) as fd, server_view("foxglove", fd) as (fx, port):
        client = FoxgloveClient(f"ws://127.0.0.1:{port}")
        try:
            want = [TOPICS["tf"], TOPICS["skin"], TOPICS["scene"]]
            client.wait_channels(want)
            topic_of = {}
            for t in want:
                ch = client.by_topic(t)
                assert ch is not None and ch["encoding"] == "protobuf"
                topic_of[client.subscribe(t)] = t
            assert client.by_topic(TOPICS["tf"])["schemaName"] == "foxglove.FrameTransforms"  # type: ignore[index]
            assert client.by_topic(TOPICS["skin"])["schemaName"] == "foxglove.SceneUpdate"  # type: ignore[index]
            decode = {t: client.decoder(client.by_topic(t)) for t in want}  # type: ignore[arg-type]
            done = {TOPICS["tf"]: lambda m: len(m.transforms) == 3, TOPICS["skin"]: lambda m: len(m.entities) == 5,
                    TOPICS["scene"]: lambda m: len(m.entities) == 2}
            seq = 0
            end = time.monotonic() + 60
            got: dict[str, Any] = {}
            while time.monotonic() < end and len(got) < 3:
                feed(fd, sk, seq)
                seq += 1
                stop = time.monotonic() + 0.1
                while time.monotonic() < stop:
                    try:
                        msg = client.ws.recv(timeout=0.05)
                    except TimeoutError:
                        continue
                    if isinstance(msg, str) or msg[0] != 1:
                        continue
                    topic = topic_of.get(struct.unpack_from("<I", msg, 1)[0])
                    if topic is not None and topic not in got:
                        m = decode[topic](msg[13:])
                        if done[topic](m):
                            got[topic] = m
            assert len(got) == 3, (list(got), fx.poll())
        finally:
            client.close()

    # the links' frames: each in its parent's, as posed at the joints' zero; the root on "skin"
    tf = {t.child_frame_id: t for t in got[TOPICS["tf"]].transforms}
    assert set(tf) == {"torso", "upper_arm", "forearm"}
    for ln in topo["links"]:
        t = tf[ln["name"]]
        assert t.parent_frame_id == (ln["parent"] or "skin")
        assert near(xyz(t.translation), [row[3] for row in ln["origin"][:3]])
        assert near(quat(t.rotation), (0.0, 0.0, 0.0, 1.0))  # the arm's links are not rotated

    # the patches: on their link, one tile per element at the topology's centre, facing its normal
    els = topo["elements"]
    centre = {b: (p, pos, nrm) for b, p, pos, nrm in zip(els["ids"], els["patch"], els["position"], els["normal"])}
    link_of = {p["name"]: p["link"] for p in topo["patches"]}
    entities = {e.id: e for e in got[TOPICS["skin"]].entities}
    assert set(entities) == {f"patch-{p['name']}" for p in topo["patches"]}
    tiles = 0
    for patch in topo["patches"]:
        e = entities[f"patch-{patch['name']}"]
        assert e.frame_id == patch["link"]
        mine = [(pos, nrm) for b, (p, pos, nrm) in centre.items() if p == patch["name"]]
        assert len(e.cubes) == len(mine) == patch["rows"] * patch["cols"]
        for cube in e.cubes:
            at = xyz(cube.pose.position)
            match = [nrm for pos, nrm in mine if near(pos, at)]
            assert len(match) == 1, (patch["name"], at)
            assert near(rotate(quat(cube.pose.orientation), (0.0, 0.0, 1.0)), match[0], 1e-6)
            tiles += 1
    assert tiles == len(els["ids"]) == 45
    assert set(link_of.values()) == set(tf)

    # the contacts: in their link's frame, an arrow along the force whose head touches the skin
    scene = {e.id: e for e in got[TOPICS["scene"]].entities}
    assert set(scene) == {f"contact-{c['id']}" for c in published}
    for c in published:
        e = scene[f"contact-{c['id']}"]
        assert e.frame_id == c["link"]
        (arrow,) = e.arrows
        fv = c["force_vector"]
        size = math.sqrt(sum(v * v for v in fv))
        assert size == pytest.approx(c["force"])
        u = [v / size for v in fv]
        direction = rotate(quat(arrow.pose.orientation), (1.0, 0.0, 0.0))
        assert near(direction, u, 1e-6), (direction, u)
        tip = [t + (arrow.shaft_length + arrow.head_length) * d for t, d in zip(xyz(arrow.pose.position), direction)]
        assert math.dist(tip, c["position"]) < 0.005, (tip, c["position"])  # on the tile over the skin
        assert math.dist(xyz(arrow.pose.position), c["position"]) > 0.01  # it comes from outside
        (disk,) = e.cylinders
        assert math.dist(xyz(disk.pose.position), c["position"]) < 0.005
        assert disk.size.x == pytest.approx(c["diameter"])


@needs_chromium
def test_the_web_page_draws_the_skin_patch_by_patch(tmp_path: Path) -> None:
    sk = rp.skin()
    forces = rp.pressed(sk)
    with FakeDaemon(layout=rp.layout(sk), reply=rp.reply(sk)) as fd, server_view("web", fd) as (web, port), \
            browser(tmp_path) as page:
        page.navigate(f"http://127.0.0.1:{port}/")
        seq = 0
        end = time.monotonic() + 60
        while time.monotonic() < end:
            feed(fd, sk, seq)
            seq += 1
            time.sleep(0.1)
            if page.evaluate("!!(typeof cellbridge !== 'undefined' && cellbridge.frame && cellbridge.frame.patches.length === 5 && "
                             "cellbridge.frame.contacts.length === 2 && cellbridge.frame.cells.some(c => c.touched))"):
                break
        page.wait_for("cellbridge.patchTitles === 5", what="the patches' titles drawn")
        frame = page.evaluate("cellbridge.frame")
        titles = {p["title"] for p in frame["patches"]}
        assert titles == {"torso / chest_left", "torso / chest_right", "upper_arm / upper_low (around)",
                          "upper_arm / upper_high (around)", "forearm / forearm (around)"}
        # every element on its patch's block, at its own row and column
        blocks = {p["title"].split(" / ")[1].split(" ")[0]: p for p in frame["patches"]}
        topo = rp.topology(sk)["skin"]["elements"]
        cells = {c["bridge"]: c for c in frame["cells"]}
        for b, p, r, c in zip(topo["ids"], topo["patch"], topo["row"], topo["col"]):
            assert (cells[b]["row"], cells[b]["col"]) == (blocks[p]["row0"] + r, blocks[p]["col0"] + c), b
        # no two patches share a cell, and none is drawn over another's title
        assert len({(c["row"], c["col"]) for c in frame["cells"]}) == 45
        title_cells = {(p["row0"] + p["rows"], p["col0"] + k) for p in frame["patches"] for k in range(p["cols"])}
        assert not title_cells & {(c["row"], c["col"]) for c in frame["cells"]}
        # the contacts on their patch's block, over the pressed element
        for k in frame["contacts"]:
            b = k["id"] - 7
            pname, r, c = rp.PRESSES[b][:3]
            blk = blocks[pname]
            assert blk["col0"] + c <= k["col"] <= blk["col0"] + c + 1 and blk["row0"] + r <= k["row"] <= blk["row0"] + r + 1
            assert k["line"].startswith(f"#{k['id']}  on ")
        text = page.evaluate("document.querySelector('#contacts').textContent")
        assert "on forearm/forearm" in text and "on torso/chest_right" in text
        png = page.screenshot(tmp_path / "robot.png")
        for b, f in [*forces.items(), (sk.element_id("upper_low", 0, 2), 0.0)]:
            rect = page.evaluate(f"cellbridge.elementRect({b})")
            want = level_rgb(f / 5.0)
            # a contact's disk and label may lie over part of it: most of it is in the colour of its force
            got = [pixel(png, rect["x"] + u * rect["w"], rect["y"] + v * rect["h"])
                   for u in (0.15, 0.5, 0.85) for v in (0.15, 0.5, 0.85)]
            assert sum(all(abs(g - w) <= 8 for g, w in zip(rgb, want)) for rgb in got) >= 4, (b, f, got, want)
        assert web.poll() is None


def test_watch_shows_the_skin_patch_by_patch() -> None:
    sk = rp.skin()
    with FakeDaemon(layout=rp.layout(sk), reply=rp.reply(sk)) as fd, \
            pty_program([CLI, "watch", *args(fd)], cols=100, rows=40) as watch:
        seq = 0
        end = time.monotonic() + 60
        while time.monotonic() < end:
            feed(fd, sk, seq)
            seq += 1
            try:
                watch.wait_for("on forearm/forearm", timeout=0.2)
                break
            except AssertionError:
                continue
        for title in ("forearm / forearm (around)", "upper_arm / upper_high (around)", "skin: arm, 45 elements in 5 "
                      "patches on 3 links"):
            watch.wait_for(title.replace("(", r"\(").replace(")", r"\)"), timeout=10)
        watch.wait_for(r"#8  on torso/chest_right", timeout=10)
        assert watch.proc.poll() is None


@needs_chromium
@pytest.mark.skipif(not os.environ.get("CELLBRIDGE_PICTURES"), reason="writes a picture only: set CELLBRIDGE_PICTURES")
def test_picture_of_the_web_page_of_the_whole_robot_demo(tmp_path: Path) -> None:
    """The arm of ``cellbridge robot run`` (MuJoCo presses fingers on it, the emulated skin and
    the daemon's core in virtual time): the daemon's messages at the moment of the most
    contacts, replayed to ``cellbridge web``."""
    pytest.importorskip("mujoco")
    from cellbridge.emulator.mesh.skin_mesh import mesh_from_skin
    from cellbridge.emulator.world.robot_world import TimelineWorld, scenario, simulate

    from cellbridge.skin_run import run_daemon_on_skin

    sk = rp.skin()
    presses = scenario(sk, 24, 0)  # cellbridge robot run's default scenario
    seconds = max(p.end for p in presses) + 0.2
    world = TimelineWorld(mesh_from_skin(sk), simulate(sk, presses, seconds))
    newest: dict[str, Any] = {}
    readings: dict[int, tuple[Any, ...]] = {}  # each element's newest reading (an element message is one line's)
    columns = ("force", "area", "dc1", "dc2", "valid", "touched", "status", "t_sample")
    best: tuple[tuple[float, ...], dict[str, Any]] | None = None
    for _, topic, m in run_daemon_on_skin(sk, world, seconds, seed=0):
        if topic in ("topology", "health"):
            newest[topic] = m
        elif topic == "element":
            for k, b in enumerate(m["bridge"]):
                readings[b] = tuple(m[c][k] for c in columns)
        elif topic == "contact" and "topology" in newest and m["contacts"]:
            score = (len(m["contacts"]), len({c["link"] for c in m["contacts"]}),
                     sum(c["force"] for c in m["contacts"] if c["force"] is not None))
            if best is None or score > best[0]:
                ids = sorted(readings)
                element = {"v": 2, "bridge": ids, **{c: [readings[b][i] for b in ids] for i, c in enumerate(columns)}}
                best = (score, {"topology": newest["topology"], "element": element, "contact": m,
                                "health": newest.get("health")})
    assert best is not None, "the run published no contact"
    shot = best[1]

    def answer(request: Any) -> Any:
        rid = request.get("id") if isinstance(request, dict) else None
        return dict(shot["topology"], id=rid, ok=True)

    with FakeDaemon(reply=answer) as fd, server_view("web", fd) as (web, port), browser(tmp_path) as page:
        page.navigate(f"http://127.0.0.1:{port}/")
        end = time.monotonic() + 60
        seq = 0
        while time.monotonic() < end:
            for topic in ("topology", "element", "contact", "health"):
                if shot[topic] is not None:
                    fd.publish(topic, dict(shot[topic], seq=seq, source="robot:5560"))
            seq += 1
            time.sleep(0.1)
            if page.evaluate("!!(typeof cellbridge !== 'undefined' && cellbridge.frame && cellbridge.frame.patches.length === 5 && "
                             f"cellbridge.frame.contacts.length === {len(shot['contact']['contacts'])})"):
                break
        time.sleep(0.5)
        picture("web-robot.png", page.screenshot())

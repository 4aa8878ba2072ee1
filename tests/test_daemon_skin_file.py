"""`cellbridge daemon` whose ``[layout] file`` is a skin description: the service built as
the command builds it (:func:`~cellbridge.daemon.shell.service.build_service`) publishes each
contact on its link, in the link frame, and the description in ``topology``; a SIGHUP that
names another skin file publishes the new one, and its contacts on the new links.

The skin's gateway lines are frame-level traffic (:class:`SkinTraffic`, what ``cellbridge
mesh traffic`` writes) replayed in recorded time; ZeroMQ on ``inproc://``, estimates inline.
"""

from __future__ import annotations

import math
import resource
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq
import zmq.asyncio
from cellbridge.daemon.core.config import load_config
from cellbridge.daemon.shell.capture import CaptureWriter
from cellbridge.daemon.shell.contact_worker import InlineExecutor
from cellbridge.daemon.shell.service import Service, build_service
from cellbridge.emulator.mesh.skin_mesh import mesh_from_skin
from cellbridge.emulator.mesh.skin_traffic import SkinTraffic
from cellbridge.emulator.world.world import Contact, World
from cellbridge.tactile.skin_geometry import SkinGeometry, parse_skin

from support.pub_helpers import run_subscriber
from support.service_messages import service_messages
from support.shell_fakes import RecordingHooks
from support.skin_descriptions import SKIN

T0 = 1_800_000_000.0
SECONDS = 4.0


def _write_skin(tmp: Path, name: str, text: str) -> Path:
    path = tmp / name
    path.write_text(text, encoding="utf-8")
    return path


def _traffic(tmp: Path, skin_text: str, press: Contact) -> list[str]:
    """Captures of the skin's gateway lines under ``press``; the link names."""
    skin = parse_skin(skin_text, "skin")
    traffic = SkinTraffic(skin, World(mesh_from_skin(skin), [press]))
    writers = {g: CaptureWriter(str(tmp / f"gateway-{g}.cbcap")) for g in traffic.gateways}
    try:
        for w in writers.values():
            w.write(T0, b"")
        for t, g, data in traffic.run(SECONDS):
            writers[g].write(T0 + t, data)
    finally:
        for w in writers.values():
            w.close()
    return [f"gateway-{g}" for g in traffic.gateways]


def _config(tmp: Path, layout: Path, links: list[str], endpoint: str) -> Path:
    text = (f'[layout]\nfile = "{layout}"\n[contact]\nrate = 1000.0\n'
            f'[pub]\nendpoint = "{endpoint}"\n[control]\nendpoint = "{endpoint}-ctl"\n')
    for n in links:
        text += (f'[[link]]\nname = "{n}"\nurl = "replay:{tmp / n}.cbcap"\nreplay_speed = 4.0\n'
                 f'replay_clock = "recorded"\nexit_when_done = true\nwait_for_subscriber = true\n')
    path = tmp / "daemon.toml"
    path.write_text(text, encoding="utf-8")
    return path


def _run(config_path: Path, endpoint: str, *, reload_to: Path | None = None) -> list[tuple[str, dict[str, Any]]]:
    """What the daemon of ``config_path`` published on ``contact`` and ``topology`` while it
    replayed; ``reload_to``: a configuration written over it and reloaded (SIGHUP) once the
    first contact arrived."""
    reloaded = [reload_to is None]

    def make(ctx: zmq.asyncio.Context) -> Service:
        config = load_config(config_path)
        return build_service(config, config_path, hooks=RecordingHooks(config), ctx=ctx,
                             contact_executor=InlineExecutor)

    def on_message(svc: Service, got: list[tuple[str, dict[str, Any]]]) -> None:
        if not reloaded[0] and got[-1][0] == "contact" and got[-1][1]["contacts"]:
            assert reload_to is not None
            config_path.write_text(reload_to.read_text(encoding="utf-8"), encoding="utf-8")
            svc.reload()
            got.append(("reloaded", {"t_host": svc.pipeline.last_feed}))
            reloaded[0] = True

    return service_messages(make, endpoint, ("contact", "topology"), on_message)


def _seam_press(skin_text: str) -> tuple[Contact, float]:
    skin = parse_skin(skin_text, "skin")
    (band,) = skin.bands
    x = band.x0 + band.period - 0.004  # 4 mm before the wrap's cut: across the seam
    return Contact(2.0, 1.5, x, 0.045, 3.0, 0.02), x - band.x0


def test_the_daemon_on_a_skin_file_publishes_contacts_on_their_link_and_the_skin_in_topology(tmp_path) -> None:
    press, along = _seam_press(SKIN)
    links = _traffic(tmp_path, SKIN, press)
    endpoint = "inproc://skin-file"
    got = _run(_config(tmp_path, _write_skin(tmp_path, "arm.toml", SKIN), links, endpoint), endpoint)
    topo = [m for t, m in got if t == "topology"]
    assert topo and topo[-1]["skin"] is not None
    assert [p["name"] for p in topo[-1]["skin"]["patches"]] == ["fore", "chest_l", "chest_r"]
    contacts = [c for t, m in got if t == "contact" for c in m["contacts"] if c["missed"] == 0]
    assert len(contacts) > 10
    assert {c["id"] for c in contacts} == {contacts[0]["id"]}  # across the wrap seam: one contact
    c = contacts[len(contacts) // 2]
    assert c["link"] == "forearm" and c["patch"] == "fore"
    skin = parse_skin(SKIN, "skin")
    angle = (along - 0.5 * skin.patches[0].col_pitch) / 0.045
    want = np.array([0.045 * math.cos(angle), 0.045 * math.sin(angle), 0.075])
    assert np.linalg.norm(np.array(c["position"]) - want) < 2e-3


def test_a_sighup_naming_another_skin_file_publishes_it_and_its_links(tmp_path) -> None:
    """The second description renames the forearm (the same atlas: the stages and the press
    held go on): once reloaded, topology says the new description and contacts are on the
    renamed link."""
    renamed = SKIN.replace('"forearm"', '"lower_arm"')
    press, _ = _seam_press(SKIN)
    links = _traffic(tmp_path, SKIN, press)
    endpoint = "inproc://skin-file-reload"
    first = _config(tmp_path, _write_skin(tmp_path, "arm.toml", SKIN), links, endpoint)
    second = tmp_path / "second.toml"
    second.write_text(first.read_text(encoding="utf-8").replace("arm.toml", "lower.toml"), encoding="utf-8")
    _write_skin(tmp_path, "lower.toml", renamed)
    got = _run(first, endpoint, reload_to=second)
    at = [t for t, _ in got].index("reloaded")
    before = [c for t, m in got[:at] if t == "contact" for c in m["contacts"]]
    assert before and {c["link"] for c in before} == {"forearm"}
    topo = [m for t, m in got[at:] if t == "topology"]
    assert topo and {ln["name"] for ln in topo[-1]["skin"]["links"]} == {"torso", "lower_arm"}
    # (messages published before the reload may still be on their way when it is made)
    after = [c for t, m in got[at:] if t == "contact" and m["t_host"] > got[at][1]["t_host"] for c in m["contacts"]]
    assert len(after) > 5 and {c["link"] for c in after} == {"lower_arm"}


def _command(args: list[str], limit: float = 30.0) -> subprocess.CompletedProcess[str]:
    """``cellbridge ARGS`` in its own process group, its memory bounded to 1.5 GB (a reader
    without a bound would take the machine's), killed with its group after ``limit`` s."""

    def bounded() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (1_500_000_000, 1_500_000_000))

    return run_subscriber([sys.executable, "-m", "cellbridge", *args], timeout=limit, preexec_fn=bounded)


@pytest.mark.process
@pytest.mark.parametrize("endless", [False, True])
def test_a_huge_or_endless_skin_file_is_refused_at_once_by_every_command_that_reads_it(tmp_path, endless) -> None:
    """A skin description is a few hundred kilobytes: a file of 40 MB (valid TOML: a
    description padded with comments) or one that never ends (/dev/zero) is refused after
    reading past the bound, by the daemon's check, mesh check and mesh traffic, naming
    the file, without a traceback; none was bounded (a gigabyte read whole, and parsed)."""
    if endless:
        path = Path("/dev/zero")
    else:
        path = tmp_path / "huge.toml"
        with open(path, "w", encoding="utf-8") as fh:
            fh.write(SKIN)
            fh.write(("#" + "x" * 98 + "\n") * 400_000)
    config = tmp_path / "daemon.toml"
    config.write_text(f'[layout]\nfile = "{path}"\n[[link]]\nname = "g"\nurl = "/dev/null"\n', encoding="utf-8")
    for args in (["daemon", "--config", str(config), "--check"], ["mesh", "check", str(path)],
                 ["mesh", "traffic", str(path), "--seconds", "1", "--out", str(tmp_path / "run")]):
        got = _command(args)
        assert got.returncode == 2, (args, got.stderr[-2000:])
        assert f"{path}: " in got.stderr and "too large" in got.stderr and "Traceback" not in got.stderr, got.stderr


def test_an_estimate_in_flight_across_a_reload_is_placed_on_the_skin_it_was_made_on() -> None:
    """The contact worker estimates on the atlas of the description the job was made with;
    a SIGHUP that names another description while it runs must not place its contacts on
    the new one's links (the same atlas x, y there is another link, another point)."""
    from cellbridge.daemon.core.config import parse_config
    from cellbridge.daemon.core.pipeline import Pipeline

    skin = parse_skin(SKIN, "arm.toml")
    other = parse_skin(SKIN.replace('"forearm"', '"lower_arm"').replace("radius = 0.045", "radius = 0.05"),
                       "other.toml")
    traffic = SkinTraffic(skin)
    config = parse_config({"link": [{"name": f"gw{g}", "url": "/dev/null"} for g in traffic.gateways]})
    pipeline = Pipeline(config, skin.layout())
    pipeline.surface = skin
    job = None
    for t, g, data in traffic.run(1.0):
        pipeline.feed(f"gw{g}", data, T0 + t)
        job = pipeline.contact_job(T0 + t) or job
    assert job is not None
    pipeline.reconfigure(config, other.layout(), other)  # the reload, while the job is estimated
    x, y = skin.atlas[skin.row_of(skin.element_id("fore", 1, 3))]
    contact = {"id": 1, "x": float(x), "y": float(y), "force": 2.0, "cov": [[1e-6, 0.0], [0.0, 1e-6]],
               "elements": [skin.element_id("fore", 1, 3)], "t": T0 + 1.0}
    (c,) = pipeline.contact_frame(job, [contact]).payload["contacts"]
    want = skin.locate([x], [y])[0]
    assert c["link"] == "forearm" and np.allclose(c["position"], want.position)


@pytest.mark.process
def test_a_toml_file_nested_too_deeply_is_refused_by_every_command_that_reads_it(tmp_path) -> None:
    """tomllib parses nested arrays recursively: a 200 kB file of brackets raised
    RecursionError, a traceback from daemon --check (as the layout file or the
    configuration), mesh check, mesh traffic and a scenario, and a SIGHUP re-reading it
    would have raised out of the reload. Each is refused naming the file."""
    deep = tmp_path / "deep.toml"
    deep.write_text("a = " + "[" * 100_000 + "]" * 100_000 + "\n", encoding="utf-8")
    skin = _write_skin(tmp_path, "arm.toml", SKIN)
    config = tmp_path / "daemon.toml"
    config.write_text(f'[layout]\nfile = "{deep}"\n[[link]]\nname = "g"\nurl = "/dev/null"\n', encoding="utf-8")
    for args in (["daemon", "--config", str(config), "--check"], ["daemon", "--config", str(deep), "--check"],
                 ["mesh", "check", str(deep)], ["mesh", "traffic", str(deep), "--out", str(tmp_path / "run")],
                 ["mesh", "traffic", str(skin), "--seconds", "1", "--scenario", str(deep),
                  "--out", str(tmp_path / "run")]):
        got = _command(args)
        assert got.returncode == 2, (args, got.stderr[-2000:])
        assert f"{deep}: " in got.stderr and "nested too deeply" in got.stderr, (args, got.stderr[-2000:])
        assert "Traceback" not in got.stderr, (args, got.stderr[-2000:])


def test_the_skin_description_in_topology_is_built_once_per_description(monkeypatch) -> None:
    """topology's ``skin`` lists every element (a skin of 62 500: 0.1 s to build), and the
    body is built at every health interval to see whether the routes changed: it was
    rebuilt each time, a tenth of a second of the event loop a second for nothing."""
    from cellbridge.daemon.core import pipeline as pipeline_module
    from cellbridge.daemon.core.config import parse_config
    from cellbridge.daemon.core.pipeline import Pipeline

    built: list[object] = []
    real = pipeline_module.skin_report

    def counting(skin: SkinGeometry | None) -> dict | None:
        built.append(skin)
        return real(skin)

    monkeypatch.setattr(pipeline_module, "skin_report", counting)
    skin = parse_skin(SKIN, "arm.toml")
    config = parse_config({"link": [{"name": "gw", "url": "/dev/null"}]})
    p = Pipeline(config, skin.layout())
    p.surface = skin
    first = [p.topology_body(float(t))["skin"] for t in range(3)]
    assert first[0] == first[2] and first[0]["name"] == "test" and len(built) == 1
    other = parse_skin(SKIN.replace('"forearm"', '"lower_arm"'), "other.toml")
    p.reconfigure(config, other.layout(), other)
    assert {ln["name"] for ln in p.topology_body(4.0)["skin"]["links"]} == {"torso", "lower_arm"}
    p.topology_body(5.0)
    assert len(built) == 2

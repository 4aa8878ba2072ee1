"""``cellbridge foxglove``: the skin as a Foxglove live connection (``foxglove-sdk``).

A Foxglove WebSocket server fed from the daemon's ZeroMQ stream through the shared view
model. It speaks the protocol under both its names, ``foxglove.sdk.v1`` (today's Foxglove
app, the SDK's server) and ``foxglove.websocket.v1`` (older Foxglove Studio, Lichtblick,
ws-protocol clients): :mod:`cellbridge.views.subprotocol` says how. Channels:

| topic | schema | what |
|---|---|---|
| ``/cellbridge/grid`` | ``foxglove.Grid`` (protobuf) | one cell per element: ``force`` (N) and ``dc1`` (pF), float32; NaN where unknown |
| ``/cellbridge/contacts`` | ``foxglove.SceneUpdate`` (protobuf) | a disk per contact (diameter, colour by force) with its id, force and diameter as text |
| ``/cellbridge/elements`` | JSON | every element's newest reading, for plots |
| ``/cellbridge/contact_list`` | JSON | the contacts as the daemon published them (id, x, y, force, diameter, ...) |
| ``/cellbridge/health`` | JSON | the daemon's health message, plus this view's own counters |

Everything is in the frame ``skin`` (the layout's frame, metres, z up). Grid, scene and
elements are published at most ``--rate`` times a second (the newest state: a plot of
an element is at that rate), health as the daemon sends it. ``docs/foxglove-layout.json``
opens these panels (``--write-layout`` writes it).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from cellbridge.daemon.subscribe import jsonable
from cellbridge.views.access import FOXGLOVE_WEB
from cellbridge.views.model import Frame, SkinView, level_rgb
from cellbridge.views.signals import ignore_stop_signals, on_stop_signal
from cellbridge.views.source import add_source_arguments, open_source
from cellbridge.views.subprotocol import LEGACY, SDK, SubprotocolFront
from cellbridge.views.web import is_loopback_host

DEFAULT_PORT = 8765
FRAME_ID = "skin"
TOPICS = {"grid": "/cellbridge/grid", "scene": "/cellbridge/contacts", "elements": "/cellbridge/elements",
          "contacts": "/cellbridge/contact_list", "health": "/cellbridge/health"}
GRID_FIELDS = ("force", "dc1")  # float32 each, in this order
CLOSE_WAIT = 0.5  #: s the clients' connections have on stop to pass the SDK server's close frames on


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Serve a running daemon's skin to Foxglove (live, over its WebSocket protocol):\n"
        f"  {TOPICS['grid']:<26} foxglove.Grid: force (N) and dc1 (pF) per element\n"
        f"  {TOPICS['scene']:<26} foxglove.SceneUpdate: a disk per contact, id/force/diameter\n"
        f"  {TOPICS['elements']:<26} JSON: every element's reading (plots)\n"
        f"  {TOPICS['contacts']:<26} JSON: the contacts\n"
        f"  {TOPICS['health']:<26} JSON: the daemon's health and this view's counters\n\n"
        "In Foxglove: Open connection -> Foxglove WebSocket -> ws://127.0.0.1:8765, then\n"
        "import the layout docs/foxglove-layout.json (or write it with --write-layout).\n"
        f"Clients offering either name of the protocol connect: {SDK} (Foxglove\n"
        f"today) or {LEGACY} (older Foxglove Studio, Lichtblick, ws-protocol clients).\n"
        "The server listens on loopback only: the protocol has no access control, so from\n"
        "another machine use an SSH tunnel (ssh -L 8765:127.0.0.1:8765 robot). A browser\n"
        f"page may connect only from Foxglove's web app ({FOXGLOVE_WEB}) or an origin\n"
        "given with --allow-origin; the desktop app (no origin) always may.\n\n"
        "examples:\n"
        "  cellbridge foxglove\n"
        "  cellbridge foxglove --port 8766 --endpoint tcp://127.0.0.1:5560\n"
        "  cellbridge foxglove --write-layout skin-layout.json"
    )
    add_source_arguments(parser)
    g = parser.add_argument_group("foxglove")
    g.add_argument("--host", default="127.0.0.1", help="loopback address to listen on (default: 127.0.0.1)")
    g.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default: {DEFAULT_PORT}; 0: any free port)")
    g.add_argument("--rate", type=float, default=30.0, metavar="HZ",
                   help="most grid/scene/element messages a second (default: 30)")
    g.add_argument("--allow-origin", action="append", default=[], metavar="URL",
                   help="a further web origin whose pages may connect (scheme://host[:port], e.g. a self-hosted "
                        f"Lichtblick); {FOXGLOVE_WEB} always may. Repeat for more")
    g.add_argument("--write-layout", type=Path, metavar="FILE",
                   help="write the Foxglove layout that opens these panels to FILE and exit")


def grid_bytes(frame: Frame) -> bytes:
    """The Grid's cell data: row-major from the layout's lowest y, (force N, ΔC1 pF) float32
    each; NaN where unknown, ±inf beyond float32's range."""
    data = np.full((frame.rows * frame.cols, 2), np.nan, dtype=np.float64)
    for c in frame.cells:
        data[c.row * frame.cols + c.col] = (c.force, c.dc1 * 1e12)
    with np.errstate(over="ignore", invalid="ignore"):
        return data.astype("<f4").tobytes()


def make_grid(frame: Frame, stamp_ns: int) -> Any:
    from foxglove.messages import (
        Grid,
        PackedElementField,
        PackedElementFieldNumericType,
        Pose,
        Quaternion,
        Timestamp,
        Vector2,
        Vector3,
    )
    return Grid(
        timestamp=Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000), frame_id=FRAME_ID,
        pose=Pose(position=Vector3(x=frame.origin[0], y=frame.origin[1], z=0.0), orientation=Quaternion(w=1.0)),
        column_count=frame.cols, cell_size=Vector2(x=frame.side, y=frame.side),
        row_stride=frame.cols * 4 * len(GRID_FIELDS), cell_stride=4 * len(GRID_FIELDS),
        fields=[PackedElementField(name=n, offset=4 * i, type=PackedElementFieldNumericType.Float32)
                for i, n in enumerate(GRID_FIELDS)],
        data=grid_bytes(frame))


def make_scene(frame: Frame, stamp_ns: int) -> Any:
    from foxglove.messages import (
        Color,
        CylinderPrimitive,
        Pose,
        Quaternion,
        SceneEntity,
        SceneEntityDeletion,
        SceneEntityDeletionType,
        SceneUpdate,
        TextPrimitive,
        Timestamp,
        Vector3,
    )
    ts = Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)
    entities = []
    for c in frame.contacts:
        if not (math.isfinite(c.x) and math.isfinite(c.y)):
            continue
        d = c.diameter_m if math.isfinite(c.diameter_m) and c.diameter_m > 0 else 0.004
        r, g, b = level_rgb(c.level)
        entities.append(SceneEntity(
            timestamp=ts, frame_id=FRAME_ID, id=f"contact-{c.id}",
            cylinders=[CylinderPrimitive(
                pose=Pose(position=Vector3(x=c.x, y=c.y, z=0.001), orientation=Quaternion(w=1.0)),
                size=Vector3(x=d, y=d, z=0.002), bottom_scale=1.0, top_scale=1.0,
                color=Color(r=r / 255, g=g / 255, b=b / 255, a=0.9))],
            texts=[TextPrimitive(
                pose=Pose(position=Vector3(x=c.x, y=c.y, z=0.01), orientation=Quaternion(w=1.0)),
                billboard=True, font_size=14.0, scale_invariant=True, color=Color(r=1.0, g=1.0, b=1.0, a=1.0),
                text=f"{c.label} ⌀{c.diameter_m * 1e3:.1f} mm" if math.isfinite(c.diameter_m) else c.label)]))
    return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=ts, type=SceneEntityDeletionType.All)],
                       entities=entities)


def elements_json(model: SkinView) -> dict[str, Any]:
    def num(v: float) -> float | None:
        return v if math.isfinite(v) else None
    return {"elements": [{"bridge": b, "force": num(e.shown_force()), "area": num(e.area),
                          "dc1_pF": num(e.dc1 * 1e12), "dc2_pF": num(e.dc2 * 1e12), "touched": e.touched,
                          "valid": e.valid, "status": e.status, "t_sample": num(e.t_sample)}
                         for b, e in sorted(model.elements.items())]}


def contacts_json(model: SkinView) -> dict[str, Any]:
    return jsonable({"t_sample": model.contact_t,
                     "contacts": [{"id": c.id, "x": c.x, "y": c.y, "force": c.force, "diameter": c.diameter,
                                   "observable": list(c.observable), "valid": c.valid, "missed": c.missed,
                                   "elements": list(c.elements)} for c in model.contacts]})


def layout() -> Any:
    """The Foxglove layout for these channels: the skin in 3D (top-down), element and
    contact force plots, health."""
    import foxglove.layouts as fl

    three_d = fl.ThreeDeePanel(title="skin", config=fl.ThreeDeeConfig(
        follow_tf=FRAME_ID,
        camera_state=fl.ThreeDeeCameraState(perspective=False, distance=0.4, phi=0.0),
        topics={
            TOPICS["grid"]: fl.BaseRendererGridTopicSettings(
                visible=True, color_mode="gradient", color_field="force", gradient=("#14183cff", "#dc1e1eff"),
                min_value=0.0, max_value=5.0, show_lines=True),
            TOPICS["scene"]: fl.BaseRendererSceneUpdateTopicSettings(visible=True),
        }))
    forces = fl.PlotPanel(title="element force (N)", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value=f"{TOPICS['elements']}.elements[:]{{bridge=={b}}}.force", label=f"bridge {b}")
        for b in (1, 2, 3, 4, 5)]))
    contact = fl.PlotPanel(title="contact force (N)", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value=f"{TOPICS['contacts']}.contacts[:].force", label="contacts")]))
    health = fl.RawMessagesPanel(title="health", config=fl.RawMessagesConfig(topic_path=TOPICS["health"]))
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=3, content=three_d),
        fl.SplitItem(proportion=2, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(proportion=1, content=forces),
            fl.SplitItem(proportion=1, content=contact),
            fl.SplitItem(proportion=1, content=health)]))]))


class FoxgloveView:
    """Channels on a running Foxglove server, fed from the model."""

    def __init__(self, model: SkinView) -> None:
        from foxglove import Channel
        from foxglove.channels import GridChannel, SceneUpdateChannel

        self.model = model
        self.grid = GridChannel(TOPICS["grid"])
        self.scene = SceneUpdateChannel(TOPICS["scene"])
        self.elements = Channel(TOPICS["elements"])
        self.contacts = Channel(TOPICS["contacts"])
        self.health = Channel(TOPICS["health"])
        self.health_seen = 0
        self.published = 0
        self.errors = 0  # frames that could not be made (counted in health's view counters)

    def publish(self, now: float) -> None:
        stamp = time.time_ns()
        frame = self.model.frame(now)
        if frame.cells and self.model.layout:  # not before the layout: no cell would be where it belongs
            self.grid.log(make_grid(frame, stamp), log_time=stamp)
        self.scene.log(make_scene(frame, stamp), log_time=stamp)
        self.elements.log(elements_json(self.model), log_time=stamp)
        self.contacts.log(contacts_json(self.model), log_time=stamp)
        seen = self.model.health_count
        if seen != self.health_seen:
            self.health_seen = seen
            self.health.log(jsonable(dict(self.model.health, view=dict(self.model.counters(), errors=self.errors),
                                          status=frame.status)), log_time=stamp)
        self.published += 1


def run(args: argparse.Namespace) -> int:
    if args.write_layout is not None:
        args.write_layout.write_text(json.dumps(json.loads(layout().to_json()), indent=1, ensure_ascii=False) + "\n")
        return 0
    problem = None
    if not 1 <= args.rate <= 240:
        problem = f"--rate must be within 1..240, got {args.rate}"
    elif not is_loopback_host(args.host):
        problem = (f"refusing to listen on {args.host}: the Foxglove protocol has no access control; "
                   "listen on loopback and use an SSH tunnel (ssh -L 8765:127.0.0.1:8765 HOST)")
    source = open_source("foxglove", args, problem)
    if source is None:
        return 2
    import foxglove

    stop = threading.Event()
    on_stop_signal(stop.set)
    server = None
    front: SubprotocolFront | None = None
    try:
        try:
            front = SubprotocolFront(args.host, args.port, 0, origins=(FOXGLOVE_WEB, *args.allow_origin))
        except OSError as exc:
            print(f"cellbridge foxglove: cannot listen on {args.host}:{args.port}: {exc.strerror or exc}",
                  file=sys.stderr)
            return 1
        try:  # the SDK's server behind the front, on a loopback port of its own
            server = foxglove.start_server(name="cellbridge", host="127.0.0.1", port=0)
        except Exception as exc:  # the SDK raises its own error types
            print(f"cellbridge foxglove: cannot start the Foxglove server: {exc}", file=sys.stderr)
            return 1
        front.upstream_port = server.port
        view = FoxgloveView(SkinView(force_scale=args.force_scale, source=args.source))
        print(f"cellbridge foxglove: ws://{args.host}:{front.port} (Foxglove WebSocket)", flush=True)
        period = 1.0 / args.rate
        last = -math.inf
        while not stop.is_set():
            wait = max(0.0, last + period - time.monotonic())
            source.poll(int(wait * 1000) if view.model.changed else 200)
            source.drain(view.model)
            now = time.monotonic()
            if now - last >= period and (view.model.changed or now - last >= 1.0):
                try:
                    view.publish(now)
                except Exception as exc:  # never end the view on a frame it could not make: counted, said once
                    view.errors += 1
                    if view.errors == 1:
                        print(f"cellbridge foxglove: error (going on, counted in /cellbridge/health): "
                              f"{type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
                last = now
    finally:
        ignore_stop_signals()  # stopping now, however it came to it
        if server is not None:
            server.stop()  # sends every client a close frame, through the front
        if front is not None:
            front.close(grace=CLOSE_WAIT if server is not None else 0.0)
        source.close()
    return 0

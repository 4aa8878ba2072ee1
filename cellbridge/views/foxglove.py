"""``cellbridge foxglove``: the skin as a Foxglove live connection (``foxglove-sdk``).

A Foxglove WebSocket server fed from the daemon's ZeroMQ stream through the shared view
model. It speaks the protocol under both its names, ``foxglove.sdk.v1`` (today's Foxglove
app, the SDK's server) and ``foxglove.websocket.v1`` (older Foxglove Studio, Lichtblick,
ws-protocol clients): :mod:`cellbridge.views.subprotocol` says how. Channels:

| topic | schema | what |
|---|---|---|
| ``/cellbridge/grid`` | ``foxglove.Grid`` (protobuf) | a flat skin: one cell per element: ``force`` (N) and ``dc1`` (pF), float32; NaN where unknown |
| ``/cellbridge/tf`` | ``foxglove.FrameTransforms`` (protobuf) | a skin on a robot: each link's frame in its parent's (roots in ``skin``) |
| ``/cellbridge/skin`` | ``foxglove.SceneUpdate`` (protobuf) | a skin on a robot: each patch on its link, a tile per element coloured by force |
| ``/cellbridge/contacts`` | ``foxglove.SceneUpdate`` (protobuf) | per contact, in its link's frame: a disk (diameter, colour by force), an arrow along its force, its id, force and diameter as text |
| ``/cellbridge/elements`` | JSON | every element's newest reading, for plots |
| ``/cellbridge/contact_list`` | JSON | the contacts as the daemon published them (id, x, y, force, diameter, ...) |
| ``/cellbridge/health`` | JSON | the daemon's health message, plus this view's own counters |

A flat skin is in the frame ``skin`` (the layout's frame, metres, z up); a skin on a robot
(a skin description: links and patches) is drawn in its links' frames, the root links
at the origin of ``skin`` (their pose at the joints' zero: the views know no joint
angles). Grid, scene and
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

from cellbridge.daemon.shell.subscribe import jsonable
from cellbridge.views.access import FOXGLOVE_WEB
from cellbridge.views.model import Contact, Frame, SkinView, level_rgb
from cellbridge.views.robot_skin import RobotSkin, quat_from_to
from cellbridge.views.signals import ignore_stop_signals, on_stop_signal
from cellbridge.views.source import add_source_arguments, open_source
from cellbridge.views.subprotocol import LEGACY, SDK, SubprotocolFront
from cellbridge.views.web import is_loopback_host

DEFAULT_PORT = 8765
FRAME_ID = "skin"
TOPICS = {"grid": "/cellbridge/grid", "scene": "/cellbridge/contacts", "elements": "/cellbridge/elements",
          "contacts": "/cellbridge/contact_list", "health": "/cellbridge/health", "skin": "/cellbridge/skin",
          "tf": "/cellbridge/tf"}
ELEMENT_THICKNESS = 0.004  #: m: an element drawn on a link is a tile this thick, its side 0.9 of the element's
ARROW_PER_N = 0.02  #: m of a contact's force arrow per newton, within ARROW_MIN..ARROW_MAX
ARROW_MIN, ARROW_MAX = 0.015, 0.12
GRID_FIELDS = ("force", "dc1")  # float32 each, in this order
CLOSE_WAIT = 0.5  #: s the clients' connections have on stop to pass the SDK server's close frames on


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Serve a running daemon's skin to Foxglove (live, over its WebSocket protocol):\n"
        f"  {TOPICS['grid']:<26} foxglove.Grid: force (N) and dc1 (pF) per element (a flat skin)\n"
        f"  {TOPICS['tf']:<26} foxglove.FrameTransforms: the robot's links (a skin on a robot)\n"
        f"  {TOPICS['skin']:<26} foxglove.SceneUpdate: each patch on its link, a tile per element\n"
        f"  {TOPICS['scene']:<26} foxglove.SceneUpdate: per contact a disk, an arrow along its\n"
        f"  {'':<26} force, id/force/diameter\n"
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


def make_scene(model: SkinView, frame: Frame, frames: dict[str, Any], robot: bool, stamp_ns: int) -> Any:
    """Per contact an entity ``contact-ID`` in the frame of its link (a flat skin: ``skin``):
    a disk of its diameter on the surface, coloured by force; an arrow along its force
    vector whose head touches the skin (none when the force is not known); a text
    ``#ID F N ⌀D mm``. Each update first deletes all earlier entities."""
    from foxglove.messages import (
        ArrowPrimitive,
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
    for c, drawn in zip(model.contacts, frame.contacts):
        place = contact_place(c, frames, robot, model.skin)
        if place is None:
            continue
        fid, p, n = place
        d = c.diameter if math.isfinite(c.diameter) and c.diameter > 0 else 0.004
        r, g, b = level_rgb(drawn.level)
        colour = Color(r=r / 255, g=g / 255, b=b / 255, a=0.9)
        qn = quat_from_to((0.0, 0.0, 1.0), n)
        lift = 0.001 + ELEMENT_THICKNESS / 2 if robot else 0.001  # on the tiles, not inside them
        centre = (p[0] + lift * n[0], p[1] + lift * n[1], p[2] + lift * n[2])
        arrows = []
        fv = c.force_vector if robot else ((0.0, 0.0, -c.force) if math.isfinite(c.force) else None)
        size = math.sqrt(sum(v * v for v in fv)) if fv is not None else 0.0
        if fv is not None and size > 0:
            u = (fv[0] / size, fv[1] / size, fv[2] / size)
            length = min(ARROW_MAX, max(ARROW_MIN, ARROW_PER_N * size))
            tail = (centre[0] - length * u[0], centre[1] - length * u[1], centre[2] - length * u[2])
            qa = quat_from_to((1.0, 0.0, 0.0), u)
            arrows.append(ArrowPrimitive(
                pose=Pose(position=Vector3(x=tail[0], y=tail[1], z=tail[2]),
                          orientation=Quaternion(x=qa[0], y=qa[1], z=qa[2], w=qa[3])),
                shaft_length=0.7 * length, shaft_diameter=0.004, head_length=0.3 * length, head_diameter=0.01,
                color=Color(r=1.0, g=1.0, b=1.0, a=1.0)))
        text_at = (centre[0] + 0.01 * n[0], centre[1] + 0.01 * n[1], centre[2] + 0.01 * n[2])
        entities.append(SceneEntity(
            timestamp=ts, frame_id=fid, id=f"contact-{c.id}", arrows=arrows,
            cylinders=[CylinderPrimitive(
                pose=Pose(position=Vector3(x=centre[0], y=centre[1], z=centre[2]),
                          orientation=Quaternion(x=qn[0], y=qn[1], z=qn[2], w=qn[3])),
                size=Vector3(x=d, y=d, z=0.002), bottom_scale=1.0, top_scale=1.0, color=colour)],
            texts=[TextPrimitive(
                pose=Pose(position=Vector3(x=text_at[0], y=text_at[1], z=text_at[2]), orientation=Quaternion(w=1.0)),
                billboard=True, font_size=14.0, scale_invariant=True, color=Color(r=1.0, g=1.0, b=1.0, a=1.0),
                text=f"{drawn.label} ⌀{c.diameter * 1e3:.1f} mm" if math.isfinite(c.diameter) else drawn.label)]))
    return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=ts, type=SceneEntityDeletionType.All)],
                       entities=entities)


def link_frames(skin: RobotSkin | None) -> dict[str, tuple[str, tuple[float, float, float],
                                                         tuple[float, float, float, float]]]:
    """Link name -> (parent frame, translation, rotation x y z w) of every link whose frame
    is known all the way to a root: its pose and every ancestor's read, no loop, no
    parent missing. Roots hang on :data:`FRAME_ID` (identity for a root at its own
    origin). A link named like that frame, or whose chain breaks, gets none: what is on
    it is listed, not drawn in 3-D."""
    if skin is None:
        return {}
    out: dict[str, tuple[str, tuple[float, float, float], tuple[float, float, float, float]]] = {}
    for name, ln in skin.links.items():
        seen: set[str] = set()
        cur: str | None = name
        ok = True
        while cur is not None:
            link = skin.links.get(cur)
            if cur in seen or cur == FRAME_ID or link is None or link.pose is None:
                ok = False
                break
            seen.add(cur)
            cur = link.parent
        if ok and ln.pose is not None:
            out[name] = (ln.parent if ln.parent is not None else FRAME_ID, ln.pose[0], ln.pose[1])
    return out


def make_transforms(frames: dict[str, Any], stamp_ns: int) -> Any:
    from foxglove.messages import FrameTransform, FrameTransforms, Quaternion, Timestamp, Vector3

    ts = Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)
    return FrameTransforms(transforms=[
        FrameTransform(timestamp=ts, parent_frame_id=parent, child_frame_id=name,
                       translation=Vector3(x=t[0], y=t[1], z=t[2]), rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))
        for name, (parent, t, q) in sorted(frames.items())])


_TILES: dict[str, Any] = {}  # the tiles' poses and colours, kept for the skin description they are of


def patch_colours(model: SkinView) -> dict[str, tuple[tuple[int, int, int], ...]]:
    """Each patch's tiles' colours (what changes from one update of its entity to the next)."""
    out: dict[str, tuple[tuple[int, int, int], ...]] = {}
    if model.skin is None:
        return out
    for patch in model.skin.patches.values():
        rgbs = []
        for b in patch.ids:
            e = model.elements.get(b)
            f = e.shown_force() if e is not None else math.nan
            rgbs.append(level_rgb(min(1.0, max(0.0, f / model.force_scale)) if math.isfinite(f) else math.nan))
        out[patch.name] = tuple(rgbs)
    return out


def make_skin_scene(model: SkinView, frames: dict[str, Any], stamp_ns: int, only: set[str] | None = None) -> Any:
    """Every patch on its link (or those named in ``only``, replacing their entities, the
    others left as they are): an entity ``patch-NAME`` in the link's frame, one tile per
    element at its centre, facing along its normal, coloured by its force (grey:
    unknown), and the patch's name as text. Patches on a link without a known frame are
    left out. A whole update first deletes all earlier entities."""
    from foxglove.messages import (
        Color,
        CubePrimitive,
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
    skin = model.skin
    entities = []
    if _TILES.get("skin") is not skin or _TILES.get("side") != model.side:  # poses: once per skin description
        _TILES.clear()
        _TILES.update(skin=skin, side=model.side, poses={}, colours={},
                      size=Vector3(x=0.9 * model.side, y=0.9 * model.side, z=ELEMENT_THICKNESS))
    poses: dict[int, Any] = _TILES["poses"]
    colours: dict[tuple[int, int, int], Any] = _TILES["colours"]
    for patch in (skin.patches.values() if skin is not None else ()):
        if patch.link not in frames or not patch.ids or (only is not None and patch.name not in only):
            continue
        cubes = []
        first = None
        for b in patch.ids:
            place = skin.elements[b]  # type: ignore[union-attr]  # skin is set when there are patches
            if place.position is None or place.normal is None:
                continue
            e = model.elements.get(b)
            f = e.shown_force() if e is not None else math.nan
            rgb = level_rgb(min(1.0, max(0.0, f / model.force_scale)) if math.isfinite(f) else math.nan)
            colour = colours.get(rgb)
            if colour is None:
                colour = colours[rgb] = Color(r=rgb[0] / 255, g=rgb[1] / 255, b=rgb[2] / 255, a=1.0)
            pose = poses.get(b)
            if pose is None:
                q = quat_from_to((0.0, 0.0, 1.0), place.normal)
                pose = poses[b] = Pose(position=Vector3(x=place.position[0], y=place.position[1], z=place.position[2]),
                                       orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))
            first = first or place
            cubes.append(CubePrimitive(pose=pose, size=_TILES["size"], color=colour))
        if first is None or first.position is None or first.normal is None:
            continue
        at = [p + 0.02 * n for p, n in zip(first.position, first.normal)]  # its name just off its first element
        entities.append(SceneEntity(
            timestamp=ts, frame_id=patch.link, id=f"patch-{patch.name}", cubes=cubes,
            texts=[TextPrimitive(pose=Pose(position=Vector3(x=at[0], y=at[1], z=at[2]), orientation=Quaternion(w=1.0)),
                                 billboard=True, font_size=12.0, scale_invariant=True,
                                 color=Color(r=0.8, g=0.85, b=0.9, a=1.0), text=patch.name)]))
    return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=ts, type=SceneEntityDeletionType.All)]
                       if only is None else [], entities=entities)


def contact_place(c: Contact, frames: dict[str, Any], robot: bool, skin: RobotSkin | None = None
                  ) -> tuple[str, tuple[float, float, float], tuple[float, float, float]] | None:
    """(frame, centre, outward normal) where a contact is drawn: on a robot, its link's
    frame with its 3-D position and normal (None when any of them is unknown, and when
    ``skin`` contradicts the link: the patch it names is not the skin's, or is another
    link's; so it is never drawn precisely in a frame it may not be in); on a flat skin,
    the frame ``skin`` at (x, y, 0), normal +z."""
    if robot:
        if c.link is None or c.link not in frames or c.position is None or c.normal is None:
            return None
        if skin is not None and c.patch is not None:
            named = skin.patches.get(c.patch)
            if named is None or named.link != c.link:
                return None
        return c.link, c.position, c.normal
    if not (math.isfinite(c.x) and math.isfinite(c.y)):
        return None
    return FRAME_ID, (c.x, c.y, 0.0), (0.0, 0.0, 1.0)


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
                                   "elements": list(c.elements), "link": c.link, "patch": c.patch,
                                   "position": c.position, "normal": c.normal, "force_vector": c.force_vector}
                                  for c in model.contacts]})


def layout() -> Any:
    """The Foxglove layout for these channels: the skin in 3D (top-down), element and
    contact force plots, health."""
    import foxglove.layouts as fl

    three_d = fl.ThreeDeePanel(title="skin", config=fl.ThreeDeeConfig(
        follow_tf=FRAME_ID,
        camera_state=fl.ThreeDeeCameraState(perspective=False, distance=0.4, phi=0.0),
        scene=fl.BaseRendererSceneSettings(transforms=fl.BaseRendererTransforms(show_label=True, axis_size=0.03)),
        topics={
            TOPICS["grid"]: fl.BaseRendererGridTopicSettings(
                visible=True, color_mode="gradient", color_field="force", gradient=("#14183cff", "#dc1e1eff"),
                min_value=0.0, max_value=5.0, show_lines=True),
            TOPICS["scene"]: fl.BaseRendererSceneUpdateTopicSettings(visible=True),
            TOPICS["skin"]: fl.BaseRendererSceneUpdateTopicSettings(visible=True),
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
        from foxglove.channels import FrameTransformsChannel, GridChannel, SceneUpdateChannel

        self.model = model
        self.grid = GridChannel(TOPICS["grid"])
        self.scene = SceneUpdateChannel(TOPICS["scene"])
        self.elements = Channel(TOPICS["elements"])
        self.contacts = Channel(TOPICS["contacts"])
        self.health = Channel(TOPICS["health"])
        self.skin = SceneUpdateChannel(TOPICS["skin"])
        self.tf = FrameTransformsChannel(TOPICS["tf"])
        self.health_seen = 0
        self._patches_of: Any = None  # the skin description whose patches were sent whole last
        self._patch_frames: set[str] = set()
        self._patches_all = -math.inf  # when (monotonic s)
        self._patch_rgb: dict[str, tuple[tuple[int, int, int], ...]] = {}
        self.published = 0
        self.errors = 0  # frames that could not be made (counted in health's view counters)

    def _publish_patches(self, frames: dict[str, Any], now: float, stamp: int) -> None:
        """The patches' tiles: all of them once a second (a client that joins gets them, and
        anything dropped is replaced) and whenever the skin description or its frames
        change; in between only the patches whose colours changed (a tile per element of a
        large skin is costly to make, and most patches are untouched)."""
        colours = patch_colours(self.model)
        whole = (self.model.skin is not self._patches_of or frames.keys() != self._patch_frames
                 or now - self._patches_all >= 1.0)
        if whole:
            self.skin.log(make_skin_scene(self.model, frames, stamp), log_time=stamp)
            self._patches_of, self._patch_frames, self._patches_all = self.model.skin, set(frames), now
        else:
            changed = {name for name, rgbs in colours.items() if self._patch_rgb.get(name) != rgbs}
            if changed:
                self.skin.log(make_skin_scene(self.model, frames, stamp, only=changed), log_time=stamp)
        self._patch_rgb = colours

    def publish(self, now: float) -> None:
        stamp = time.time_ns()
        frame = self.model.frame(now)
        robot = bool(frame.patches)  # a skin on a robot: its links' frames, its patches on them
        frames = link_frames(self.model.skin) if robot else {}
        if robot:
            self.tf.log(make_transforms(frames, stamp), log_time=stamp)
            self._publish_patches(frames, now, stamp)
        elif frame.cells and self.model.layout:  # not before the layout: no cell would be where it belongs
            self.grid.log(make_grid(frame, stamp), log_time=stamp)
        self.scene.log(make_scene(self.model, frame, frames, robot, stamp), log_time=stamp)
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
    elif not 0 <= args.port <= 65535:  # (as web: a port out of range ended in an OverflowError traceback)
        problem = f"--port must be within 0..65535, got {args.port}"
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

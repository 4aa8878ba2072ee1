"""A simulated robot as the world: MuJoCo moves an arm with skin and presses fingers on it.

The robot is a model of our own (:data:`ARM_SKIN`, :func:`arm_mjcf`): a torso whose
front carries two planar patches, an upper arm and a forearm whose skins are cylinders
wrapped around them (the upper arm's in two rings, one patch each), on a shoulder and an
elbow that move through a trajectory. *Fingers* (free spheres, pushed towards a point of the
skin by a spring whose push into the skin is clamped to the press's force) press, hold,
slide and release at places a :class:`Press` names on the skin. MuJoCo resolves the contacts; each contact's point
(in the touched link's frame, on the skin's surface), normal force and footprint (the
finger's pad: MuJoCo contacts are points) becomes a disk on the skin's atlas, and the
element physics turns the disks into capacitances as for any other stimulus
(:class:`TimelineWorld` is a :class:`~cellbridge.emulator.world.world.World`).

The simulation runs ahead of the skin (:func:`simulate`: the robot's motion does not depend
on the skin's readings) and keeps, per step, the disks and the ground truth of every
contact: link, point, normal, force, area, start and end (:class:`Truth`), which
``cellbridge robot`` scores the daemon's contacts against.

MuJoCo is the optional ``robot`` extra (``pip install 'cellbridge[robot]'``).
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from cellbridge.emulator.mesh.mesh import Mesh
from cellbridge.emulator.world.world import World
from cellbridge.tactile import ElementParams, skin_response
from cellbridge.tactile.skin_geometry import SkinGeometry, parse_skin

__all__ = ["ARM_SKIN", "Press", "Timeline", "TimelineWorld", "Truth", "arm_mjcf", "arm_skin", "scenario",
           "simulate"]

#: The arm's skin. Link frames: the torso at the world's origin; the shoulder 0.25 m up
#: the torso's front; each arm segment's axis is its link's z.
ARM_SKIN = """\
name = "arm"
side = 0.04

[[link]]
name = "torso"

[[link]]
name = "upper_arm"
parent = "torso"
origin = [0.0, 0.0, 0.25]

[[link]]
name = "forearm"
parent = "upper_arm"
origin = [0.0, 0.0, 0.30]

# the torso's front (its +x face, 0.10 m out), two patches side by side: one surface
[[patch]]
name = "chest_left"
link = "torso"
shape = "plane"
rows = 3
cols = 2
origin = [0.10, 0.02, -0.10]
rpy = [1.5707963267948966, 0.0, 1.5707963267948966]

[[patch]]
name = "chest_right"
link = "torso"
shape = "plane"
rows = 3
cols = 2
origin = [0.10, 0.10, -0.10]
rpy = [1.5707963267948966, 0.0, 1.5707963267948966]

# the upper arm: two rings of 6 around a 40 mm radius, one above the other
[[patch]]
name = "upper_low"
link = "upper_arm"
shape = "cylinder"
radius = 0.04
wrap = true
rows = 1
cols = 6
origin = [0.0, 0.0, 0.10]

[[patch]]
name = "upper_high"
link = "upper_arm"
shape = "cylinder"
radius = 0.04
wrap = true
rows = 1
cols = 6
origin = [0.0, 0.0, 0.14]

# the forearm: 7 around a 45 mm radius, 3 along
[[patch]]
name = "forearm"
link = "forearm"
shape = "cylinder"
radius = 0.045
wrap = true
rows = 3
cols = 7
origin = [0.0, 0.0, 0.08]

[[gateway]]
name = "torso"
patch = "chest_left"

[[gateway]]
name = "upper_arm"
patch = "upper_low"

[[gateway]]
name = "forearm"
patch = "forearm"
"""

#: Finger tips (sphere radius, m) and how many there are (two presses at once at most).
FINGER_RADIUS = 0.010
FINGERS = 2
FINGER_MASS = 0.02  #: kg
STEP = 0.001  #: the simulation's step (s): the timeline's resolution
#: The finger's servo: a spring to its target point (N/m) with damping (N·s/m); its push
#: into the skin is clamped to the press's force, so that is the contact's force at rest.
FINGER_KP, FINGER_KD = 300.0, 5.0
#: A contact counts from this normal force on (N): below it, a finger grazing the skin.
TOUCH = 0.05


def arm_skin() -> SkinGeometry:
    return parse_skin(ARM_SKIN, "arm skin")


def arm_mjcf(skin: SkinGeometry) -> str:
    """The arm as MJCF: link bodies named as the skin's links, collision geoms on the skin's
    outer surface (a box for the torso, cylinders for the arm), two hinges with position
    servos, and the fingers (free spheres, pushed by a force servo)."""
    fore = skin.patch("forearm")
    up = skin.patch("upper_low")
    fingers = "\n".join(
        f'<body name="finger{i}" pos="1 {i} 1"><freejoint name="finger{i}"/><geom name="finger{i}" type="sphere" '
        f'size="{FINGER_RADIUS}" mass="{FINGER_MASS}" rgba=".9 .5 .2 1" contype="2" conaffinity="1"/></body>'
        for i in range(FINGERS))
    return f"""<mujoco model="arm">
  <option timestep="{STEP}" gravity="0 0 0"/>
  <default><geom contype="1" conaffinity="2" friction="0.3 0.005 0.0001"/></default>
  <worldbody>
    <body name="torso">
      <geom name="torso" type="box" size="0.10 0.10 0.15" pos="0 0.08 -0.05" mass="20"/>
      <body name="upper_arm" pos="0 0 0.25">
        <joint name="shoulder" type="hinge" axis="1 0 0" range="-1.2 1.2" damping="5"/>
        <geom name="upper_arm" type="cylinder" size="{up.radius} 0.08" pos="0 0 0.12" mass="2"/>
        <body name="forearm" pos="0 0 0.30">
          <joint name="elbow" type="hinge" axis="1 0 0" range="-1.5 1.5" damping="5"/>
          <geom name="forearm" type="cylinder" size="{fore.radius} 0.07" pos="0 0 0.12" mass="1.5"/>
        </body>
      </body>
    </body>
    {fingers}
  </worldbody>
  <actuator>
    <position name="shoulder" joint="shoulder" kp="400" kv="20"/>
    <position name="elbow" joint="elbow" kp="300" kv="15"/>
  </actuator>
</mujoco>"""


@dataclass(frozen=True)
class Press:
    """One finger pressing: at atlas (x, y) at ``start`` (s), ramping to ``force`` (N) over
    ``ramp`` s, holding ``hold`` s (sliding at ``velocity`` m/s along the atlas meanwhile),
    then lifting over ``ramp`` s. ``pad``: the finger pad's diameter (m), the footprint."""

    finger: int
    start: float
    x: float
    y: float
    force: float
    pad: float
    hold: float
    ramp: float = 0.05
    velocity: tuple[float, float] = (0.0, 0.0)
    kind: str = "single"

    @property
    def end(self) -> float:
        return self.start + 2 * self.ramp + self.hold


@dataclass
class Truth:
    """One contact as MuJoCo made it: a finger on a link from ``start`` to ``end`` (s);
    per step (``t``) its point and normal in the link frame (on the skin's surface), normal
    force (N), and the atlas position of the point. ``area``: the footprint (m²)."""

    finger: int
    link: str
    kind: str
    area: float
    pad: float
    start: float
    end: float = math.nan
    t: list[float] = field(default_factory=list)
    point: list[tuple[float, float, float]] = field(default_factory=list)
    normal: list[tuple[float, float, float]] = field(default_factory=list)
    force: list[float] = field(default_factory=list)
    atlas: list[tuple[float, float]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"finger": self.finger, "link": self.link, "kind": self.kind, "area": self.area, "pad": self.pad,
                "start": self.start, "end": self.end, "t": self.t, "point": self.point, "normal": self.normal,
                "force": self.force, "atlas": self.atlas}


@dataclass
class Timeline:
    """What :func:`simulate` made: per step, the disks ``(x, y, force, diameter)`` on the
    atlas; and every contact's ground truth."""

    step: float
    disks: list[tuple[tuple[float, float, float, float], ...]]
    truths: list[Truth]
    seconds: float

    def at(self, t: float) -> tuple[tuple[float, float, float, float], ...]:
        k = int(math.floor(t / self.step + 1e-9))
        return self.disks[k] if 0 <= k < len(self.disks) else ()


class TimelineWorld(World):
    """The emulated skin's world from a :class:`Timeline`: each element's capacitance at
    time t from the disks of the step t falls in (the element physics as for any stimulus)."""

    def __init__(self, mesh: Mesh, timeline: Timeline, params: ElementParams | None = None, **kw: Any) -> None:
        super().__init__(mesh, [], params, **kw)
        self.timeline = timeline
        self._always = True  # contacts come from the timeline: never the untouched shortcut

    def _pressed(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        disks = self.timeline.at(t)

        def respond() -> tuple[np.ndarray, np.ndarray]:
            if not disks:
                return np.full(self.layout.n, self.rest[0]), np.full(self.layout.n, self.rest[1])
            d1, d2 = skin_response(self.layout, self.disks(list(disks)), self.params)
            return self.rest[0] + d1, self.rest[1] + d2

        return self._cached(("timeline", disks), respond)

    def sense_for(self, bridge: int):
        i = self.index[bridge]
        clock = float(self.clock_hz)

        def sense(tick: int) -> tuple[float, float]:
            c1, c2 = self.capacitances(tick / clock)
            return float(c1[i]), float(c2[i])

        return sense


def _places(skin: SkinGeometry, rng: random.Random, kind: str, pad: float) -> tuple[float, float]:
    """An atlas place for a press of ``kind``: anywhere on a patch, across a wrap seam, or
    across the seam of two patches of one link."""
    side = skin.side
    if kind == "wrap":
        b = rng.choice(skin.bands)
        x = b.x0 + rng.uniform(-0.3, 0.3) * pad
        y = rng.uniform(b.y0 + 0.3 * side, b.y1 - 0.3 * side)
        return b.wrap(x), y
    if kind == "patch_seam":
        if rng.random() < 0.5:  # the chest: between left and right
            c = next(ch for ch in skin.charts if ch.link == "torso")
            x = c.x0 + 2 * side + rng.uniform(-0.3, 0.3) * pad
            y = rng.uniform(c.y0 + 0.3 * side, c.y0 + c.height - 0.3 * side)
        else:  # the upper arm: between its two rings
            c = next(ch for ch in skin.charts if ch.link == "upper_arm")
            x = c.x0 + rng.uniform(0.0, c.width)
            y = c.y0 + side + rng.uniform(-0.3, 0.3) * pad
        return x, y
    c = rng.choice(skin.charts)
    margin = 0.5 * pad if c.period else 0.5 * pad + 0.003
    x = c.x0 + rng.uniform(margin if not c.period else 0.0, c.width - (margin if not c.period else 0.0))
    y = rng.uniform(c.y0 + margin + 0.003, c.y0 + c.height - margin - 0.003)
    return x, y


def scenario(skin: SkinGeometry, contacts: int, seed: int = 0, gap: float = 0.25) -> list[Press]:
    """A scripted scenario of at least ``contacts`` contacts: single presses anywhere,
    presses across wrap seams and across the seam of two patches of one link, slides, and
    two presses at once (on different links, or far apart on one), ``gap`` s apart."""
    rng = random.Random(seed)
    presses: list[Press] = []
    t = 3.0  # the skin forms its routes and calibrates first
    kinds = ["single", "single", "wrap", "patch_seam", "slide", "two"]
    n = 0
    while n < contacts:
        before = len(presses)
        kind = kinds[len(presses) % len(kinds)] if presses else "single"
        pad = rng.uniform(0.014, 0.024)
        hold = rng.uniform(0.35, 0.6)
        force = rng.uniform(1.5, 4.5)
        if kind == "two":
            a = _places(skin, rng, "single", pad)
            for _ in range(50):
                b = _places(skin, rng, "single", pad)
                if math.hypot(a[0] - b[0], a[1] - b[1]) > 3.5 * skin.side:
                    break
            presses.append(Press(0, t, *a, force, pad, hold, kind="two"))
            presses.append(Press(1, t + 0.03, *b, rng.uniform(1.5, 4.5), rng.uniform(0.014, 0.024), hold, kind="two"))
            n += 2
        elif kind == "slide":
            x, y = _places(skin, rng, "single", pad)
            c = skin.charts[int(skin.chart_at([x], [y])[0])]
            speed = rng.uniform(0.02, 0.05)
            vx = speed if (c.period or x < c.x0 + 0.5 * c.width) else -speed
            if not c.period:
                hold = min(hold, max(0.2, (c.width - pad) / 2 / speed))
            presses.append(Press(0, t, x, y, force, pad, hold, velocity=(vx, 0.0), kind="slide"))
            n += 1
        else:
            x, y = _places(skin, rng, kind, pad)
            presses.append(Press(0, t, x, y, force, pad, hold, kind=kind))
            n += 1
        t = max(p.end for p in presses[before:]) + gap  # each starts after every earlier one ended: linear
    return presses


def _arm_angles(t: float) -> tuple[float, float]:
    """The arm's trajectory: a slow swing of the shoulder and the elbow (rad)."""
    return 0.5 * math.sin(0.21 * t), 0.7 * math.sin(0.33 * t + 0.5)


def simulate(skin: SkinGeometry, presses: list[Press], seconds: float) -> Timeline:
    """Run MuJoCo for ``seconds`` with the arm moving and the fingers pressing: the timeline
    of disks on the atlas and the ground truth of every contact."""
    import mujoco  # type: ignore[import-untyped]  # no type information published

    model = mujoco.MjModel.from_xml_string(arm_mjcf(skin))
    data = mujoco.MjData(model)
    body = {ln.name: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, ln.name) for ln in skin.links}
    finger_geom = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"finger{i}") for i in range(FINGERS)]
    finger_body = [int(model.geom_bodyid[g]) for g in finger_geom]
    finger_q = [int(model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"finger{i}")])
                for i in range(FINGERS)]
    finger_v = [int(model.jnt_dofadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"finger{i}")])
                for i in range(FINGERS)]
    finger_of = {g: i for i, g in enumerate(finger_geom)}
    link_of_body = {b: name for name, b in body.items()}
    parked = [np.array([1.0, float(i), 1.0]) for i in range(FINGERS)]
    active: list[Press | None] = [None] * FINGERS
    todo = sorted(presses, key=lambda p: p.start)
    open_truth: dict[int, Truth] = {}
    truths: list[Truth] = []
    steps = int(round(seconds / STEP))
    disks: list[tuple[tuple[float, float, float, float], ...]] = []

    def park(i: int) -> None:
        data.qpos[finger_q[i]:finger_q[i] + 3] = parked[i]
        data.qvel[finger_v[i]:finger_v[i] + 6] = 0.0
        data.xfrc_applied[finger_body[i]] = 0.0

    for i in range(FINGERS):
        park(i)
    for k in range(steps):
        t = k * STEP
        sh, el = _arm_angles(t)
        data.ctrl[0], data.ctrl[1] = sh, el
        started = []
        while todo and todo[0].start <= t:
            new = todo.pop(0)
            active[new.finger] = new
            started.append(new.finger)
        for i in range(FINGERS):
            p = active[i]
            if p is None:
                continue
            tp = t - p.start
            if tp > p.end - p.start + 0.05:
                active[i] = None
                park(i)
                continue
            slide = min(max(tp - p.ramp, 0.0), p.hold)
            x, y = p.x + p.velocity[0] * slide, p.y + p.velocity[1] * slide
            x = skin.wrap_x(x, y)
            (sp,) = skin.locate([x], [y])
            b = body[sp.link]
            rot = data.xmat[b].reshape(3, 3)
            n = rot @ np.array(sp.normal)
            surface = data.xpos[b] + rot @ np.array(sp.position)
            if i in started:  # a few mm off the skin, at rest relative to it
                data.qpos[finger_q[i]:finger_q[i] + 3] = surface + n * (FINGER_RADIUS + 0.003)
                data.qvel[finger_v[i]:finger_v[i] + 6] = 0.0
            if tp < p.ramp:
                push = p.force * tp / p.ramp
            elif tp < p.ramp + p.hold:
                push = p.force
            elif tp < 2 * p.ramp + p.hold:
                push = p.force * (2 * p.ramp + p.hold - tp) / p.ramp
            else:
                push = -0.5  # lift off
            pos = data.qpos[finger_q[i]:finger_q[i] + 3]
            vel = data.qvel[finger_v[i]:finger_v[i] + 3]
            # where the skin's point moves (the finger follows it); the spring aims 30 mm into the skin, its
            # push along the normal clamped below: it is the press's force that the skin holds up
            vs = np.zeros(6)
            mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_XBODY, b, vs, 0)
            v_surf = vs[3:] + np.cross(vs[:3], surface - data.xpos[b])
            target = surface + n * (FINGER_RADIUS - 0.030)
            f = FINGER_KP * (target - pos) - FINGER_KD * (vel - v_surf)
            fn = float(f @ n)
            f += n * (max(fn, -push) - fn)  # the push into the skin: the press's force at most
            data.xfrc_applied[finger_body[i], :3] = f
            data.xfrc_applied[finger_body[i], 3:] = 0.0
        mujoco.mj_step(model, data)
        # the contacts of this step: finger -> (link, force, force-weighted point)
        sums: dict[int, list[Any]] = {}
        f6 = np.zeros(6)
        for c in range(data.ncon):
            con = data.contact[c]
            g1, g2 = int(con.geom1), int(con.geom2)
            if g1 in finger_of:
                fi, other = finger_of[g1], g2
            elif g2 in finger_of:
                fi, other = finger_of[g2], g1
            else:
                continue
            mujoco.mj_contactForce(model, data, c, f6)
            fn = float(f6[0])
            if fn <= 0:
                continue
            link = link_of_body.get(int(model.geom_bodyid[other]))
            if link is None:
                continue
            s = sums.setdefault(fi, [link, 0.0, np.zeros(3)])
            s[1] += fn
            s[2] += fn * np.asarray(con.pos)
        step_disks = []
        for i in range(FINGERS):
            got = sums.get(i)
            if got is None or got[1] < TOUCH:
                if i in open_truth:
                    ended = open_truth.pop(i)
                    ended.end = t
                    truths.append(ended)
                continue
            link, fsum, wpos = got
            b = body[link]
            rot = data.xmat[b].reshape(3, 3)
            local = rot.T @ (wpos / fsum - data.xpos[b])
            at = skin.atlas_of(link, local)
            if at is None:
                continue
            ax, ay, _ = at
            ax = skin.wrap_x(ax, ay)
            (sp,) = skin.locate([ax], [ay])
            by = active[i]
            pad = by.pad if by is not None else 0.02
            old = open_truth.get(i)
            if old is None or old.link != link:
                if old is not None:
                    old.end = t
                    truths.append(old)
                open_truth[i] = Truth(i, link, by.kind if by is not None else "stray", math.pi * pad * pad / 4, pad, t)
            tr = open_truth[i]
            tr.t.append(t)
            tr.point.append(sp.position)
            tr.normal.append(sp.normal)
            tr.force.append(fsum)
            tr.atlas.append((ax, ay))
            step_disks.append((ax, ay, fsum, pad))
        disks.append(tuple(step_disks))
    for tr in open_truth.values():
        tr.end = seconds
        truths.append(tr)
    truths.sort(key=lambda tr: tr.start)
    return Timeline(STEP, disks, truths, seconds)

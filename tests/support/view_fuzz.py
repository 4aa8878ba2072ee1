"""Random and mistyped daemon messages for the views' fuzz test: ``element``, ``contact``,
``health`` and ``topology`` payloads shaped like the daemon's (docs/zmq-api.md; with a
skin on a robot: topology's ``skin`` with its links, patches and element frames, and
contacts' link, patch, 3-D position, normal and force vector), then
mutated: NaN, ±inf, ±1e308, huge integers, wrong types, huge arrays, deep nesting,
control characters in every string; and messages that are not payloads at all (not
msgpack, a map keyed by an array, one or three frames, a topic that only begins like one).

:func:`messages` is deterministic in its seed: a failure is replayed by its seed.
"""

from __future__ import annotations

import math
import random
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import msgpack

TOPICS = ("element", "contact", "health", "topology")
SOURCE = "fuzz:5560"
# what a terminal would act on: OSC 52 (clipboard), OSC 0 (title), CSI colour, cursor
# report request, DCS, C1 CSI, BEL, bidi override, NUL
NASTY = ["\x1b]52;c;cHduZWQ=\x07", "\x1b]0;pwned\x07", "\x1b[31m", "\x1b[6n", "\x1bP+q544e\x1b\\", "\x9b31m",
         "\x07", "\u202e", "\x00", "\x1b", "\r", "\x1b[?1049l", "\x1bc"]
ODD_NUMBERS = [math.nan, math.inf, -math.inf, 1e308, -1e308, 5e-324, 0.0, -0.0, 2**63 - 1, -(2**63), 2**64 - 1, 0, -1]


@dataclass
class Message:
    frames: list[bytes]
    topic: str | None  # the topic a view counts it under (None: not counted under a topic)
    shown: bool  # a payload of the source the views show


def nasty_text(rng: random.Random) -> str:
    """A string with control characters (and sometimes a long one)."""
    parts = [rng.choice(NASTY) if rng.random() < 0.6 else chr(rng.randrange(0, 0x2100)) for _ in range(rng.randrange(1, 8))]
    if rng.random() < 0.002:
        parts.append("x" * rng.randrange(1000, 20_000))
    return "gw" + "".join(parts)


def odd_value(rng: random.Random, depth: int = 0) -> Any:
    r = rng.random()
    if r < 0.35:
        return rng.choice(ODD_NUMBERS)
    if r < 0.5:
        return nasty_text(rng)
    if r < 0.6:
        return rng.choice([None, True, False, b"\x1b[31m", b""])
    if r < 0.7 and depth < 3:
        return [odd_value(rng, depth + 1) for _ in range(rng.randrange(0, 4))]
    if r < 0.8 and depth < 3:
        return {nasty_text(rng): odd_value(rng, depth + 1) for _ in range(rng.randrange(0, 4))}
    if r < 0.85:
        return deep(rng.randrange(50, 300))
    return rng.uniform(-1e3, 1e3)


def deep(n: int) -> Any:
    v: Any = 1.0
    for i in range(n):
        v = [v] if i % 2 else {"a": v}
    return v


def column(rng: random.Random, n: int, good: Any) -> list[Any]:
    if n > 1000:  # a huge array: odd numbers in it, not odd structures (the test's time goes to the views)
        return [rng.choice(ODD_NUMBERS) if i % 7 == 0 else good(i) for i in range(n)]
    return [odd_value(rng) if rng.random() < 0.3 else good(i) for i in range(n)]


def element(rng: random.Random, seq: int) -> dict[str, Any]:
    n = rng.randrange(1, 20) if rng.random() > 0.003 else rng.randrange(50_000, 120_000)
    return {"v": 1, "seq": seq, "t_host": 1e9, "t_bridge": [0] * min(n, 10),
            "bridge": column(rng, n, lambda i: rng.randrange(0, 64) if rng.random() < 0.98 else rng.randrange(0, 70_000)),
            "force": column(rng, n, lambda i: rng.uniform(-1, 10)),
            "area": column(rng, n, lambda i: 1e-4), "dc1": column(rng, n, lambda i: rng.uniform(0, 3e-12)),
            "dc2": column(rng, n, lambda i: 1e-12), "valid": column(rng, n, lambda i: rng.random() < 0.8),
            "touched": column(rng, n, lambda i: rng.random() < 0.5),
            "status": column(rng, n, lambda i: rng.randrange(0, 16)),
            "t_sample": column(rng, n, lambda i: float(seq))}


LINKS = ["torso", "upper_arm", "forearm"]


def vector(rng: random.Random, good: Any) -> Any:
    """A 3-vector: mostly ``good()``, sometimes with odd numbers in it or of another length."""
    r = rng.random()
    if r < 0.6:
        return good()
    if r < 0.8:
        return [rng.choice(ODD_NUMBERS) if rng.random() < 0.5 else x for x in good()]
    if r < 0.9:
        return [rng.uniform(-1, 1) for _ in range(rng.choice([0, 1, 2, 4, 100]))]
    return odd_value(rng)


def pose(rng: random.Random) -> Any:
    """A 4×4 pose: the identity moved, or scaled, mirrored, with odd numbers, of the wrong shape."""
    m = [[1.0, 0.0, 0.0, rng.uniform(-0.3, 0.3)], [0.0, 1.0, 0.0, rng.uniform(-0.3, 0.3)],
         [0.0, 0.0, 1.0, rng.uniform(-0.3, 0.3)], [0.0, 0.0, 0.0, 1.0]]
    r = rng.random()
    if r < 0.6:
        return m
    if r < 0.7:
        m[0][0] = rng.choice([2.0, -1.0, 0.0])
    elif r < 0.85:
        m[rng.randrange(4)][rng.randrange(4)] = rng.choice(ODD_NUMBERS)
    else:
        return odd_value(rng)
    return m


def robot_contact(rng: random.Random, c: dict[str, Any]) -> dict[str, Any]:
    """``c`` with the fields a daemon with a skin description adds."""
    f = c["force"] if isinstance(c["force"], float) else 1.0
    c.update(link=rng.choice([*LINKS, None, nasty_text(rng), 5]), patch=rng.choice(["forearm", "chest_left", None,
                                                                                   nasty_text(rng)]),
             position=vector(rng, lambda: [rng.uniform(-0.2, 0.2) for _ in range(3)]),
             normal=vector(rng, lambda: [rng.uniform(-1, 1) for _ in range(3)]),
             force_vector=vector(rng, lambda: [0.0, 0.0, -f]) if rng.random() < 0.9 else None,
             position_cov=odd_value(rng))
    return c


def contact(rng: random.Random, seq: int) -> dict[str, Any]:
    n = rng.randrange(0, 5) if rng.random() > 0.003 else rng.randrange(1000, 20_000)
    robot = rng.random() < 0.5
    contacts = [{"id": rng.randrange(0, 100), "x": rng.uniform(-0.1, 0.3), "y": rng.uniform(-0.1, 0.3),
                 "force": rng.uniform(0, 10), "diameter": rng.uniform(0, 0.05), "observable": [True, rng.random() < 0.5],
                 "valid": True, "missed": 0, "sigma_x": 1e-4, "sigma_y": 0.004, "elements": [1, 2],
                 "label": nasty_text(rng) if n < 10 else "\x1b[31m"} for _ in range(n)]
    if robot and n < 10:
        contacts = [robot_contact(rng, c) for c in contacts]
    return {"v": 2, "seq": seq, "t_sample": 1.0, "contacts": contacts}


def skin(rng: random.Random, n: int) -> Any:
    """A ``skin`` map for a layout of ids 1..n: links (some posed oddly, some in a loop),
    patches (some of odd sizes or names), element frames (some odd), now and then huge."""
    if rng.random() < 0.1:
        return odd_value(rng)
    links = [{"name": name, "parent": parent, "origin": pose(rng), "declared": True}
             for name, parent in zip(LINKS, [None, "torso", "upper_arm"])]
    if rng.random() < 0.1:
        links[0]["parent"] = "forearm"  # a loop
    if rng.random() < 0.1:
        links.append({"name": rng.choice(["skin", nasty_text(rng), "", 7]), "parent": odd_value(rng), "origin": pose(rng)})
    if rng.random() < 0.003:
        links += [{"name": f"l{i}", "parent": f"l{i - 1}", "origin": pose(rng)} for i in range(5000)]
    npatch = rng.randrange(1, 5)
    names = [rng.choice(["forearm", "chest_left", f"p{k}", nasty_text(rng)]) for k in range(npatch)]
    patches = [{"name": name, "link": rng.choice([*LINKS, nasty_text(rng)]),
                "shape": rng.choice(["plane", "cylinder", odd_value(rng)]),
                "rows": rng.choice([1, 2, 3, 4, 0, -1, 10**9, math.nan, "3"]) if rng.random() < 0.3 else rng.randrange(1, 5),
                "cols": rng.randrange(1, 8), "pitch": rng.choice([0.04, 0.04, math.nan, -1.0, 1e308]),
                "col_pitch": rng.choice([0.04, 0.04, 0.0, math.inf]), "wrap": rng.choice([True, False, "yes"]),
                "pose": pose(rng), "start": [0.0, 0.0], "first_id": 1} for name in names]
    if rng.random() < 0.003:
        patches += [{"name": f"q{i}", "link": "torso", "rows": 128, "cols": 128} for i in range(2000)]
    k = n if rng.random() > 0.01 else rng.randrange(20_000, 80_000)
    elements = {"ids": column(rng, k, lambda i: i + 1),
                "patch": column(rng, k, lambda i: rng.choice(names)),
                "row": column(rng, k, lambda i: rng.randrange(0, 5)),
                "col": column(rng, k, lambda i: rng.randrange(0, 8)),
                "position": [vector(rng, lambda: [rng.uniform(-0.2, 0.2) for _ in range(3)]) for _ in range(min(k, 200))],
                "normal": [vector(rng, lambda: [0.0, 0.0, 1.0]) for _ in range(min(k, 200))]}
    return {"name": nasty_text(rng), "side": 0.04, "urdf": None, "links": links, "patches": patches,
            "gateways": [{"name": nasty_text(rng), "bridge": 1}], "elements": elements}


def health(rng: random.Random, seq: int) -> dict[str, Any]:
    links = {nasty_text(rng): {"connected": rng.random() < 0.5, "error": nasty_text(rng)} for _ in range(rng.randrange(1, 4))}
    if rng.random() < 0.002:
        links.update({f"l{i}\x1b[{i}m": {"connected": True} for i in range(50_000)})
    bridges = {str(b): {"silent": rng.random() < 0.1, "lost": rng.randrange(0, 9), "frames": rng.randrange(0, 999),
                        "sample_rate": 100.0} for b in range(rng.randrange(0, 20))}
    return {"v": 1, "seq": seq, "uptime": float(seq), "links": links, "bridges": bridges,
            "contact_estimation": {"last_ms": 1.0, "max_ms": 2.0},
            "layout": {"calibration": {"ready": rng.randrange(0, 9), "collecting": nasty_text(rng)},
                       "source": nasty_text(rng)},
            "pub": {"dropped": {"element": rng.choice([0, 1, math.inf, 1e308, -1e308, math.nan, "x"])}},
            "note": nasty_text(rng)}


def topology(rng: random.Random, seq: int) -> dict[str, Any]:
    n = rng.randrange(1, 30) if rng.random() > 0.003 else rng.randrange(20_000, 80_000)
    side = rng.choice([0.04, 0.04, 0.0002, 1e-300, 5e-324, 0.0, -0.04, math.nan, math.inf, 1e308, "0.04"])
    out = {"v": 1, "seq": seq, "bridges": {}, "gateways": {nasty_text(rng): [1]},
           "layout": {"side": side, "ids": column(rng, n, lambda i: i + 1),
                      "x": column(rng, n, lambda i: rng.choice([i * 0.04, 1e308, -1e308, i * 1e3])),
                      "y": column(rng, n, lambda i: rng.choice([0.0, (i % 4) * 0.04, 1e300]))}}
    if rng.random() < 0.5:  # a daemon with a skin description (schema 2)
        out.update(v=2, skin=skin(rng, min(n, 1000)))
    return out


MAKERS = {"element": element, "contact": contact, "health": health, "topology": topology}


def mutate(rng: random.Random, payload: dict[str, Any]) -> Any:
    """Some fields of ``payload`` replaced by odd values, dropped, or the whole of it replaced."""
    r = rng.random()
    if r < 0.05:
        return odd_value(rng)  # not a map at all
    for key in list(payload):
        x = rng.random()
        if x < 0.15:
            payload[key] = odd_value(rng)
        elif x < 0.2:
            del payload[key]
    if rng.random() < 0.1:
        payload[nasty_text(rng)] = odd_value(rng)
    return payload


def messages(seed: int, n: int) -> Iterator[Message]:
    """``n`` messages: mostly mutated payloads of the four topics from :data:`SOURCE`, some
    of other or mistyped sources, some that are not payloads."""
    rng = random.Random(seed)
    seqs = dict.fromkeys(TOPICS, 0)
    for _ in range(n):
        r = rng.random()
        topic = rng.choice(TOPICS)
        if r < 0.03:  # not msgpack, or a map keyed by an array, or too deep for msgpack
            body = rng.choice([bytes(rng.randrange(256) for _ in range(rng.randrange(0, 40))),
                               b"\x81\x91\x01\x01", b"\x91" * 5000 + b"\xc0", b"\xdd\xff\xff\xff\xff"])
            try:  # random bytes are sometimes a msgpack value after all: then a (mistyped) payload
                msgpack.unpackb(body, raw=False, strict_map_key=False)
                counted: str | None = topic
            except Exception:
                counted = None
            yield Message([topic.encode(), body], counted, False)
            continue
        if r < 0.05:  # one or three frames
            yield Message(rng.choice([[topic.encode()], [topic.encode(), b"\x80", b"x"]]), None, False)
            continue
        if r < 0.07:  # a topic that only begins like one (a subscription is a prefix)
            frames = [(topic + rng.choice(["s", "\x1b[31m", "_v2", "\x00"])).encode("utf-8", "surrogatepass"),
                      msgpack.packb({"v": 1, "seq": 0, "source": SOURCE}, use_bin_type=True)]
            yield Message(frames, None, False)
            continue
        seqs[topic] += 1
        payload = mutate(rng, MAKERS[topic](rng, seqs[topic]))
        shown = True
        if isinstance(payload, dict):
            s = rng.random()
            if s < 0.9:
                payload["source"] = SOURCE
            elif s < 0.95:
                payload["source"] = nasty_text(rng)
                shown = False
            else:
                payload["source"] = odd_value(rng)
                shown = payload["source"] == SOURCE
        yield Message([topic.encode(), msgpack.packb(payload, use_bin_type=True)], topic, shown)

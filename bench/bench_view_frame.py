"""What one picture of the views' model costs: ``SkinView.frame`` (every view calls it once a
refresh: watch 30, web 60, foxglove 30 a second) and, for a skin on a robot, the Foxglove
messages made from it (transforms, the patches' tiles, the contacts' disks and arrows).

Run: ``.venv/bin/python bench/bench_view_frame.py``. In process, no sockets: the model is
fed a ``topology`` (with or without a skin description), every element's reading and a
``contact`` message, then asked for frames. Skins:

- *flat 64×64*: 4096 elements on one plane, the largest the model keeps;
- *robot 16 patches*: the same 4096 elements as 16 patches of 16×16 on 4 links, drawn
  patch by patch;
- *arm*: the 45 elements of ``cellbridge robot run``'s arm.

Each with 2 and with 64 contacts (the most a ``contact`` message is read for); with a
skin on a robot, the Foxglove messages of an update that sends the one patch whose
colours changed (as ``cellbridge foxglove`` does between its whole updates) and of a
whole update (once a second). Prints the median and the slowest of 20 frames, in ms.
"""

from __future__ import annotations

import statistics
import time
from typing import Any

from cellbridge.views import foxglove as fx
from cellbridge.views.model import SkinView

IDENTITY = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


def big_skin(robot: bool) -> tuple[dict[str, Any], list[int]]:
    n, k_patches, side = 16, 16, 0.04
    ids: list[int] = []
    cols: dict[str, list[Any]] = {k: [] for k in ("patch", "row", "col", "position", "normal", "x", "y")}
    for k in range(k_patches):
        for r in range(n):
            for c in range(n):
                b = len(ids) + 1
                ids.append(b)
                cols["patch"].append(f"p{k}")
                cols["row"].append(r)
                cols["col"].append(c)
                cols["position"].append([c * side, r * side, 0.0])
                cols["normal"].append([0.0, 0.0, 1.0])
                if robot:
                    cols["x"].append(k * (n + 2) * side + c * side)
                    cols["y"].append(r * side)
                else:
                    cols["x"].append(((b - 1) % 64) * side)
                    cols["y"].append(((b - 1) // 64) * side)
    topo: dict[str, Any] = {"v": 2, "seq": 0, "layout": {"side": side, "ids": ids, "x": cols["x"], "y": cols["y"]}}
    if robot:
        topo["skin"] = {
            "name": "big", "links": [{"name": f"l{i}", "parent": None, "origin": IDENTITY} for i in range(4)],
            "patches": [{"name": f"p{k}", "link": f"l{k % 4}", "shape": "plane", "rows": n, "cols": n, "pitch": side,
                         "col_pitch": side, "wrap": False} for k in range(k_patches)],
            "elements": {"ids": ids, **{k: cols[k] for k in ("patch", "row", "col", "position", "normal")}}}
    return topo, ids


def contacts_on(topo: dict[str, Any], n: int) -> dict[str, Any]:
    xs, ys = topo["layout"]["x"], topo["layout"]["y"]
    step = max(1, len(xs) // n)
    out = []
    for i in range(n):
        k = (i * step) % len(xs)
        c: dict[str, Any] = {"id": i, "x": xs[k] + 0.005, "y": ys[k], "force": 2.0, "diameter": 0.015}
        skin = topo.get("skin")
        if skin is not None:
            el = skin["elements"]
            patch = next(p for p in skin["patches"] if p["name"] == el["patch"][k])
            c.update(link=patch["link"], patch=patch["name"], position=el["position"][k], normal=el["normal"][k],
                     force_vector=[-2.0 * v for v in el["normal"][k]])
        out.append(c)
    return {"v": 2, "seq": 0, "contacts": out}


def measure(topo: dict[str, Any], ids: list[int], n_contacts: int, reps: int = 20, whole: bool = False
            ) -> tuple[float, float, float]:
    m = SkinView()
    m.feed("topology", topo, 0.0)
    m.feed("element", {"v": 2, "seq": 0, "bridge": ids, "force": [1.0] * len(ids), "valid": [True] * len(ids)}, 0.0)
    m.feed("contact", contacts_on(topo, n_contacts), 0.0)
    frame_ms, fox_ms = [], []
    # the patches sent: all of them (once a second, as cellbridge foxglove does), or one
    # patch whose colours changed (a press on one patch: the updates in between)
    changed = None if whole else {next(iter(m.skin.patches))} if m.skin is not None else set()
    for _ in range(reps):
        t0 = time.perf_counter()
        f = m.frame(0.0)
        t1 = time.perf_counter()
        frames = fx.link_frames(m.skin) if f.patches else {}
        if f.patches:
            fx.make_transforms(frames, 1).encode()
            fx.patch_colours(m)
            fx.make_skin_scene(m, frames, 1, only=changed).encode()
        else:
            fx.make_grid(f, 1).encode()
        fx.make_scene(m, f, frames, bool(f.patches), 1).encode()
        t2 = time.perf_counter()
        frame_ms.append((t1 - t0) * 1e3)
        fox_ms.append((t2 - t1) * 1e3)
    return statistics.median(frame_ms), max(frame_ms), statistics.median(fox_ms)


def main() -> None:
    import robot_payloads as rp

    arm = rp.skin()
    skins = [("flat 64x64", *big_skin(False)), ("robot 16 patches", *big_skin(True)),
             ("arm (45)", rp.topology(arm), [int(b) for b in arm.ids.tolist()])]
    print("skin              contacts  patches sent  frame p50 ms  frame max ms  foxglove msgs p50 ms")
    print("----------------  --------  ------------  ------------  ------------  --------------------")
    for name, topo, ids in skins:
        for n, whole in ((2, False), (64, False), (64, True)):
            if whole and not topo.get("skin"):
                continue
            p50, worst, fox = measure(topo, ids, n, whole=whole)
            sent = "-" if not topo.get("skin") else "all" if whole else "one changed"
            print(f"{name:<16}  {n:>8}  {sent:>12}  {p50:>12.2f}  {worst:>12.2f}  {fox:>20.2f}")


if __name__ == "__main__":
    main()

"""The committed capture and its golden daemon output (tests/data/daemon_press.*).

``python tests/support/daemon_golden.py`` regenerates both; do that only when a deliberate
change of the daemon's output is reviewed, and commit the new golden file with it.

The capture is a gateway line carrying nine bridges (3 x 3): HELLO and BEACON, quiet
samples for the baseline, a 3 N press on the corner of four elements, the release, a
second press held to the end, with
line noise and a truncated frame on the way, in reads of uneven size.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

DATA = Path(__file__).resolve().parents[1] / "data"
CAPTURE = DATA / "daemon_press.cbcap"
GOLDEN = DATA / "daemon_press.golden.json"
CONFIG = DATA / "daemon_press.toml"
PRESS = (0.020, 0.020, 3.0, 0.012)  # the corner of bridges 1, 2, 4 and 5
PRESS2 = (0.040, 0.022, 2.0, 0.010)  # across the seam of bridges 2 and 5
T0 = 1_750_000_000.0


def make_capture(path: Path) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))  # run as a script too
    from cellbridge.daemon.shell.capture import write_capture

    from daemon_traffic import Skin

    sk = Skin(rows=3, cols=3)
    records = [(T0, sk.hellos() + sk.beacons())]
    plan = [(None, 15), (PRESS, 10), (None, 8), (PRESS2, 12)]
    k = 0
    for press, n in plan:
        for _ in range(n):
            data = sk.slot(k, press)
            if k == 20:
                one = data.split(b"\x00")[1]
                data = b"\x00noise\x00" + one[:7] + b"\x00" + data
            t = T0 + 0.01 + k / sk.rate
            if k % 3 == 0:  # a read that splits the slot in two
                cut = len(data) // 3
                records += [(t, data[:cut]), (t + 0.0004, data[cut:])]
            else:
                records.append((t, data))
            k += 1
    write_capture(path, records)


CONTACT_KEYS = ("x", "y", "force", "diameter", "elements", "valid")
#: Tolerances of the contact comparison: the estimator may improve without breaking the
#: golden file, but not move a contact by half a millimetre or change its force by 1 %.
CONTACT_TOL = {"x": 5e-4, "y": 5e-4, "diameter": 5e-4}
CONTACT_REL = {"force": 0.01}


def normalise(messages: list[tuple[str, dict[str, Any]]]) -> dict[str, Any]:
    """What the golden file holds: every element message, and the last contact estimate
    (its time stamps and each contact's position, force, diameter, elements, validity)."""
    # ``source`` names the daemon that published (its host name by default), not what it computed
    elements = [{k: v for k, v in m.items() if k != "source"} for t, m in messages if t == "element"]
    contacts = [m for t, m in messages if t == "contact"]
    last = None
    if contacts:
        m = contacts[-1]
        last = {"t_host": m["t_host"], "t_sample": m["t_sample"],
                "contacts": [{k: c[k] for k in CONTACT_KEYS} for c in m["contacts"]]}
    return {"element": elements, "last_contact": last}


def compare(got: dict[str, Any], golden: dict[str, Any]) -> list[str]:
    """Element messages equal to 1e-9; the last contact within the physical tolerances."""
    diffs = close(got["element"], golden["element"], "element")
    a, b = got["last_contact"], golden["last_contact"]
    if a is None or b is None:
        return diffs + ([] if a is b else [f"last_contact: {a!r} != {b!r}"])
    diffs += close(a["t_host"], b["t_host"], "t_host") + close(a["t_sample"], b["t_sample"], "t_sample")
    if len(a["contacts"]) != len(b["contacts"]):
        return diffs + [f"contacts: {len(a['contacts'])} != {len(b['contacts'])}"]
    for i, (x, y) in enumerate(zip(a["contacts"], b["contacts"])):
        for k in CONTACT_KEYS:
            if k in CONTACT_TOL:
                ok = abs(x[k] - y[k]) <= CONTACT_TOL[k]
            elif k in CONTACT_REL:
                ok = math.isclose(x[k], y[k], rel_tol=CONTACT_REL[k])
            else:
                ok = (sorted(x[k]) == sorted(y[k])) if k == "elements" else x[k] == y[k]
            if not ok:
                diffs.append(f"contacts[{i}].{k}: {x[k]!r} != {y[k]!r}")
    return diffs


def pipeline_output() -> dict[str, Any]:
    """Replay the capture through the daemon offline (its core and its contact loop's
    schedule, in the capture's time) with the golden config."""
    from cellbridge.daemon.core.config import load_config
    from cellbridge.daemon.shell.capture import read_capture
    from cellbridge.daemon.shell.offline import OfflineDaemon

    # (the golden config replays the capture in recorded time: a look takes the last read's time)
    d = OfflineDaemon(load_config(CONFIG), topics={"element", "contact"}, recorded=True)
    out = [(o.topic, o.payload) for o in d.run((t, "gw", data) for t, data in read_capture(CAPTURE))]
    return normalise(out)


def close(a: Any, b: Any, path: str = "") -> list[str]:
    """Differences between two JSON-like values; floats equal to 1e-9 relative (NaN == NaN)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{path}: keys differ: {sorted(set(a) ^ set(b))}"]
        return [d for k in a for d in close(a[k], b[k], f"{path}.{k}")]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: length {len(a)} != {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in close(x, y, f"{path}[{i}]")]
    if isinstance(a, float) or isinstance(b, float):
        if isinstance(a, bool) or isinstance(b, bool) or a is None or b is None:
            return [] if a == b else [f"{path}: {a!r} != {b!r}"]
        if math.isnan(a) and math.isnan(b):
            return []
        return [] if math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-24) else [f"{path}: {a!r} != {b!r}"]
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


def load_golden() -> dict[str, Any]:
    return json.loads(GOLDEN.read_text())


if __name__ == "__main__":
    make_capture(CAPTURE)
    GOLDEN.write_text(json.dumps(pipeline_output(), indent=None, separators=(",", ":")) + "\n")
    print(f"wrote {CAPTURE} ({CAPTURE.stat().st_size} bytes) and {GOLDEN} ({GOLDEN.stat().st_size} bytes)")

"""The golden corpus: recordings of gateway lines and the daemon's output on them.

Most scenarios below run the deterministic virtual mesh (``cellbridge.emulator.mesh.virtual``),
keep every gateway's serial bytes with their virtual arrival times as a recording's
``serial`` channel (what ``cellbridge record --serial`` keeps from a live daemon); a
scenario with a ``capture`` instead writes hand-crafted frames (``bench/daemon_traffic.py``)
as a link's capture file (``NAME.cbcap``, what a link's ``capture`` keeps, which the real
daemon replays) and runs the daemon with its own config file. Next to each recording is the
daemon's output on it as one line per message (``NAME.chk``: ``element`` and ``contact``
messages with their fields rounded to what matters, and a last ``health`` line with the
counters a scenario exercises), so a change of the daemon's output is a readable ``diff``.
``tests/test_golden_corpus.py`` replays them all; :func:`published_diff` checks what a
running daemon published against the same lines. The files live in ``tests/data/golden/``
with ``README.md`` saying how each was made (the same note is in each MCAP recording's
``cellbridge`` metadata).

Commands (from the repository root)::

    .venv/bin/python tests/support/golden_corpus.py --regen     # the daemon's output changed on purpose:
                                                        # rewrite every .chk from the recordings
    .venv/bin/python tests/support/golden_corpus.py --remake    # the emulator changed: run the mesh again,
                                                        # rewrite the recordings and the .chk files
    .venv/bin/python tests/support/golden_corpus.py --diff      # what would change, as a unified diff

then review ``git diff tests/data/golden`` and commit it with the change that caused it.
"""

from __future__ import annotations

import argparse
import difflib
import math
import sys
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

DATA = Path(__file__).resolve().parents[1] / "data" / "golden"
T0 = 1_750_000_000.0  #: host time (epoch) of virtual time 0
READ_GRAIN = 0.001  #: s; a host read returns what arrived within this (a pty read's batching)


@dataclass(frozen=True)
class Scenario:
    name: str
    note: str  #: how it was made, for README.md and the recording's metadata
    mesh: Callable[[], Any] | None  #: None: the reads come from ``capture``
    seconds: float
    presses: tuple[tuple[float, float, float, float, float, float], ...] = ()  # start, duration, x, y, F, d
    restart: tuple[tuple[int, float], ...] = ()  # (bridge, at)
    adc: bool = False
    transform: str = ""  # "fragments", "wrap24", "noise": what is done to the gateway's bytes
    config: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: writes ``NAME.cbcap`` (a link's capture, link ``CAPTURE_LINK``): the reads, instead of the mesh
    capture: Callable[[Path], None] | None = None
    #: a daemon config in ``DATA`` the scenario runs with instead of ``BASE_CONFIG`` + ``config``
    config_file: str = ""


def _grid(rows: int, cols: int, gateways: tuple[int, ...] = (1,)) -> Callable[[], Any]:
    def make() -> Any:
        from cellbridge.emulator.mesh import meshgen
        return meshgen.grid(rows, cols, gateways=gateways)
    return make


def _line(n: int) -> Callable[[], Any]:
    def make() -> Any:
        from cellbridge.emulator.mesh import meshgen
        return meshgen.line(n)
    return make


CAPTURE_LINK = "gw"  #: the link a capture scenario's reads come in on (its config's one link)
PRESS = (0.020, 0.020, 3.0, 0.012)  #: daemon_press's first press: the corner of bridges 1, 2, 4 and 5
PRESS2 = (0.040, 0.022, 2.0, 0.010)  #: its second, held to the end: across the seam of bridges 2 and 5


def make_press_capture(path: Path) -> None:
    """daemon_press: a gateway line carrying nine bridges (3 x 3) at 100 Hz: HELLO and BEACON,
    15 quiet slots for the baseline, ``PRESS`` for 10, the release for 8, ``PRESS2`` for 12;
    line noise and a truncated frame in slot 20, every third slot read in two pieces."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))  # run as a script too
    from cellbridge.daemon.shell.capture import write_capture

    from daemon_traffic import GridFrames

    sk = GridFrames(rows=3, cols=3)
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
    path.unlink(missing_ok=True)  # (a capture writer keeps a file it would overwrite as NAME.1)
    write_capture(path, records)


SCENARIOS: tuple[Scenario, ...] = (
    Scenario("multihop_line", "a line of 6 bridges, gateway at bridge 1 (up to 5 hops); a 3 N press on "
             "bridge 5's element from 1.0 s to 2.0 s", _line(6), 2.5,
             presses=((1.0, 1.0, 0.180, 0.020, 3.0, 0.02),)),
    Scenario("two_gateways", "a 3x3 grid with gateways at bridges 1 and 9, one link each (gw1, gw9), each bridge "
             "routing to one of them; a 2 N press across a seam between two elements from 1.0 s to 2.0 s",
             _grid(3, 3, (1, 9)), 2.5, presses=((1.0, 1.0, 0.080, 0.060, 2.0, 0.015),)),
    Scenario("fragments", "a 2x2 grid whose gateway line carries its DATA frames split into fragments of at "
             "most 40 bytes (cellbridge.protocol.fragment, each origin's frames renumbered as a bridge that "
             "fragments numbers them); a 3 N press on the corner of all four from 1.0 s to 2.0 s",
             _grid(2, 2), 2.5, presses=((1.0, 1.0, 0.040, 0.040, 3.0, 0.02),), transform="fragments"),
    Scenario("adc_mode", "a 2x2 grid sampling with the 8-bit ADC (16 conversions a sample) instead of the "
             "counter; a 3 N press on bridge 2's element from 1.0 s to 2.0 s", _grid(2, 2), 2.5,
             presses=((1.0, 1.0, 0.060, 0.020, 3.0, 0.02),), adc=True),
    Scenario("bridge_reset", "a 3x3 grid; bridge 5 (the centre) is power-cycled at 1.0 s and boots again "
             "(HELLO numbered 0, its cycle counter from 0); a 3 N press on it from 1.6 s to 2.4 s",
             _grid(3, 3), 3.0, presses=((1.6, 0.8, 0.060, 0.060, 3.0, 0.02),), restart=((5, 1.0),)),
    Scenario("counter_wrap", "a 2x2 grid whose bridges' cycle counters are 24 bits wide (the samples' cycle "
             "field taken modulo 2**24: it wraps every 0.34 s), daemon chip.cycle_bits = 24; a 3 N press "
             "from 1.0 s to 2.0 s across the seam of bridges 2 and 4 (a press on every element of a skin at once, "
             "as a corner press of a 2x2 skin is on mesh time, is what common-mode drift looks like)",
             _grid(2, 2), 2.5, presses=((1.0, 1.0, 0.040, 0.020, 3.0, 0.02),),
             transform="wrap24", config={"chip": {"cycle_bits": 24}}),
    Scenario("line_noise", "a 2x2 grid whose gateway line picks up noise: every 25th read gets 7 stray bytes, "
             "every 40th loses its last 5 bytes (a cut frame), every 55th has one bit flipped; a 3 N press from "
             "1.0 s to 2.0 s", _grid(2, 2), 2.5, presses=((1.0, 1.0, 0.040, 0.020, 3.0, 0.02),),
             transform="noise"),
    Scenario("daemon_press", "a capture (`daemon_press.cbcap`, replayed with `daemon_press.toml`) of a gateway line "
             "carrying a 3x3 grid's DATA frames at 100 Hz, hand-crafted (bench/daemon_traffic.py): 15 quiet "
             "slots, a 3 N press on the corner of bridges 1, 2, 4 and 5 for 10, the release for 8, a 2 N press "
             "across the seam of bridges 2 and 5 held to the end; line noise and a truncated frame in slot 20, "
             "every third slot read in two pieces", None, 0.45, capture=make_press_capture,
             config_file="daemon_press.toml"),
)

BASE_CONFIG: dict[str, dict[str, Any]] = {
    "calibration": {"n_baseline": 20},
    "contact": {"birth_frames": 2},
}


# -- making recordings ---------------------------------------------------------------------
def run_mesh(sc: Scenario) -> dict[int, list[tuple[float, bytes]]]:
    """Every gateway's serial output as (virtual time, bytes) chunks."""
    from cellbridge.emulator.firmware.commands import Settings
    from cellbridge.emulator.mesh.virtual import CLOCK_HZ, VirtualMesh
    from cellbridge.emulator.world.world import Contact
    from cellbridge.protocol import Mode

    out: dict[int, list[tuple[float, bytes]]] = {}

    class Recording(VirtualMesh):
        def _gateway_out(self, b: int, data: bytes) -> None:
            super()._gateway_out(b, data)
            out.setdefault(b, []).append((self.tick / CLOCK_HZ, data))

    if sc.mesh is None:
        raise ValueError(f"{sc.name}: no mesh to run (its reads come from a capture)")
    settings = Settings(mode=Mode.ADC) if sc.adc else Settings()
    vm = Recording(sc.mesh(), seed=1, settings=settings)
    for start, duration, x, y, force, diameter in sc.presses:
        vm.press(Contact(start, duration, x, y, force, diameter))
    for bridge, at in sc.restart:
        vm.restart(bridge, at)
    vm.run(sc.seconds)
    return out


def _reframe(chunks: list[tuple[float, bytes]], edit: Callable[[Any], list[Any]]) -> list[tuple[float, bytes]]:
    from cellbridge.protocol import StreamDecoder, encode_stream

    dec = StreamDecoder()
    out = []
    for t, data in chunks:
        frames = [g for f in dec.feed(data) for g in edit(f)]
        if frames:
            out.append((t, b"".join(encode_stream(f) for f in frames)))
    return out


def _fragments(chunks: list[tuple[float, bytes]]) -> list[tuple[float, bytes]]:
    from cellbridge.protocol import FrameType
    from cellbridge.protocol.fragment import fragment

    seqs: dict[int, int] = {}

    def edit(f: Any) -> list[Any]:
        pieces = fragment(f, seqs.get(f.origin, 0), 40) if f.type is FrameType.DATA else [f]
        out = []
        for p in pieces:
            out.append(replace(p, seq=seqs.get(f.origin, 0) & 0xFFFF))
            seqs[f.origin] = seqs.get(f.origin, 0) + 1
        return out

    return _reframe(chunks, edit)


def _wrap24(chunks: list[tuple[float, bytes]]) -> list[tuple[float, bytes]]:
    from cellbridge.protocol import FrameType

    def edit(f: Any) -> list[Any]:
        if f.type is FrameType.DATA:
            f.payload.samples = [s._replace(cycle=s.cycle % (1 << 24)) for s in f.payload.samples]
        return [f]

    return _reframe(chunks, edit)


def host_reads(chunks: list[tuple[float, bytes]], transform: str) -> list[tuple[float, bytes]]:
    """The chunks as a host reads them: what arrived within READ_GRAIN in one read, at its end."""
    if transform == "fragments":
        chunks = _fragments(chunks)
    elif transform == "wrap24":
        chunks = _wrap24(chunks)
    reads: list[tuple[float, bytearray]] = []
    for t, data in chunks:
        at = math.ceil(t / READ_GRAIN - 1e-9) * READ_GRAIN
        if reads and reads[-1][0] == at:
            reads[-1][1].extend(data)
        else:
            reads.append((at, bytearray(data)))
    out = []
    for i, (t, buf) in enumerate(reads):
        b = bytes(buf)
        if transform == "noise":
            if i % 25 == 24:
                b = b"\x13\x37noise" + b
            if i % 40 == 39:
                b = b[:-5]
            if i % 55 == 54 and len(b) > 8:
                b = b[:8] + bytes([b[8] ^ 0x10]) + b[9:]
        out.append((T0 + t, b))
    return out


def make_recording(sc: Scenario, path: Path) -> None:
    if sc.capture is not None:
        sc.capture(path)
        return
    from cellbridge.recording import codec
    from cellbridge.recording.mcapfile import RecordingWriter

    w = RecordingWriter(path, chunk_size=256 * 1024, fsync=False,
                        metadata={"scenario": sc.name, "note": sc.note, "made_by": "tests/support/golden_corpus.py --remake",
                                  "seed": "1", "t0": repr(T0)})
    reads = sorted((t, f"gw{g}", data) for g, chunks in run_mesh(sc).items() for t, data in host_reads(chunks, sc.transform))
    seq = 0
    for t, link, data in reads:
        payload = {"v": 1, "seq": seq, "t_host": t, "t_bridge": None, "link": link, "data": data,
                   "source": "virtual-mesh"}
        w.add("serial", codec.encode("serial", payload), int(t * 1e9), int(t * 1e9), seq)
        seq += 1
    w.finish()


# -- the daemon's output -------------------------------------------------------------------
def config_for(sc: Scenario, links: list[str]) -> Any:
    from cellbridge.daemon.core.config import load_config, parse_config

    if sc.config_file:
        return load_config(DATA / sc.config_file)
    data: dict[str, Any] = {k: dict(v) for k, v in BASE_CONFIG.items()}
    for k, v in sc.config.items():
        data.setdefault(k, {}).update(v)
    data["link"] = [{"name": n, "url": f"/dev/null-{n}"} for n in links]
    return parse_config(data, f"golden {sc.name}")


def serial_reads(path: Path) -> list[tuple[str, float, bytes]]:
    """(link, host time, bytes) of every read of a recording (or of a capture, on ``CAPTURE_LINK``)."""
    if path.suffix == ".cbcap":
        from cellbridge.daemon.shell.capture import read_capture
        return [(CAPTURE_LINK, t, data) for t, data in read_capture(path)]
    from cellbridge.recording import codec
    from cellbridge.recording.mcapfile import read_messages

    out = []
    for m in read_messages(path, topics={"serial"}):
        p = codec.decode("serial", m.data)
        out.append((p["link"], p["t_host"], p["data"]))
    return out


def offline_run(sc: Scenario, recording: Path) -> tuple[list[tuple[str, dict[str, Any]]], list[dict[str, Any]]]:
    """The daemon on the recording's reads: its core and its contact loop's schedule (ticks,
    pacing at ``[contact] rate``) in the recording's time (a look at the last read's time
    when the config replays in recorded time, as the service then does), contacts through
    the production contact path (an inline worker). Its element and contact messages in
    order, and the health it then publishes."""
    from cellbridge.daemon.core.messages import Publish
    from cellbridge.daemon.shell.offline import OfflineDaemon

    reads = serial_reads(recording)
    cfg = config_for(sc, sorted({link for link, _, _ in reads}))
    recorded = any(link.replay_clock == "recorded" and link.url.startswith("replay:") for link in cfg.links)
    d = OfflineDaemon(cfg, topics={"element", "contact"}, recorded=recorded)
    messages = [(o.topic, o.payload) for o in d.run((t, link, data) for link, t, data in reads)]
    p = d.pipeline
    p.want({"health"})
    t = reads[-1][1] if reads else T0
    health = [m.payload for m in p.tick(t, force=True) if isinstance(m, Publish) and m.topic == "health"]
    return messages, health


def daemon_output(sc: Scenario, recording: Path) -> list[str]:
    """:func:`offline_run` one line per message (the ``.chk`` form), a last ``health``."""
    messages, health = offline_run(sc, recording)
    return [render(t, m) for t, m in messages] + [render("health", m) for m in health]


def _f(v: Any, scale: float, digits: int) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    text = f"{v * scale:.{digits}f}"
    return text[1:] if text.startswith("-") and not text.strip("-0.") else text  # no "-0.0"


def _observable(obs: Any) -> str:
    """``observable`` as two letters: ``xy`` both axes pinned by the readings, ``x-``, ``-y``, ``--``."""
    if not isinstance(obs, (list, tuple)) or len(obs) != 2:
        return "?"
    return ("x" if obs[0] else "-") + ("y" if obs[1] else "-")


def _col(m: dict[str, Any], key: str, scale: float, digits: int) -> str:
    return ",".join(_f(v, scale, digits) for v in m[key])


def render(topic: str, m: dict[str, Any]) -> str:
    """One message as one line: the fields a reviewer judges, rounded to their meaning."""
    t = f"t={m['t_host'] - T0:.4f}"
    if topic == "element":
        return (f"element {t} b={','.join(map(str, m['bridge']))} cycle={','.join(map(str, m['cycle']))} "
                f"c1={_col(m, 'c1', 1e12, 4)}pF c2={_col(m, 'c2', 1e12, 4)}pF "
                f"dc1={_col(m, 'dc1', 1e15, 1)}fF dc2={_col(m, 'dc2', 1e15, 1)}fF "
                f"F={_col(m, 'force', 1, 3)}N S={_col(m, 'area', 1e6, 1)}mm2 "
                f"touched={''.join('1' if x else '0' for x in m['touched'])}")
    if topic == "contact":
        ts = m["t_sample"]
        parts = [f"contact {t} t_sample={_f(ts - T0 if ts is not None else None, 1, 4)} n={len(m['contacts'])}"]
        if m.get("unknown"):
            parts.append(f"unknown={','.join(map(str, m['unknown']))}")
        for c in sorted(m["contacts"], key=lambda c: c["id"]):
            parts.append(f"| id={c['id']} x={_f(c['x'], 1e3, 1)}mm y={_f(c['y'], 1e3, 1)}mm "
                         f"sx={_f(c['sigma_x'], 1e3, 1)}mm sy={_f(c['sigma_y'], 1e3, 1)}mm "
                         f"F={_f(c['force'], 1, 2)}N d={_f(c['diameter'], 1e3, 1)}mm "
                         f"A={_f(c.get('area'), 1e6, 1)}mm2 obs={_observable(c.get('observable'))} "
                         f"elements={','.join(map(str, sorted(c['elements'])))} valid={int(bool(c['valid']))}")
            if c.get("unknown_near"):
                parts.append(f"unknown_near={','.join(map(str, c['unknown_near']))}")
        return " ".join(parts)
    if topic == "health":
        bridges = m.get("bridges", {})
        per = " ".join(f"b{b}:frames={h.get('frames')},lost={h.get('lost')},restarts={h.get('seq_restarts')},"
                       f"clock_resets={h.get('clock_resets')}" for b, h in sorted(bridges.items(), key=lambda x: int(x[0])))
        links = " ".join(f"{n}:frames={h.get('frames')},crc={h.get('crc_errors')},framing={h.get('framing_errors')}"
                         for n, h in sorted(m.get("links", {}).items()))
        r = m.get("reassembly", {})
        return (f"health {t} duplicates={m.get('duplicates')} reassembly_completed={r.get('completed')} "
                f"reassembly_drops={sum((r.get('drops') or {}).values())} {links} {per}")
    raise ValueError(f"no line format for topic {topic!r}")


# -- the corpus on disk ----------------------------------------------------------------------
def paths(sc: Scenario) -> tuple[Path, Path]:
    """The scenario's recording (``.mcap``, or its capture ``.cbcap``) and its ``.chk``."""
    return DATA / f"{sc.name}{'.cbcap' if sc.capture else '.mcap'}", DATA / f"{sc.name}.chk"


def scenario(name: str) -> Scenario:
    return next(sc for sc in SCENARIOS if sc.name == name)


def expected(sc: Scenario) -> list[str]:
    return paths(sc)[1].read_text().splitlines()


def diff(sc: Scenario, got: list[str]) -> list[str]:
    mcap, chk = paths(sc)
    return list(difflib.unified_diff(expected(sc), got, f"{chk.name} (committed)", f"{chk.name} (daemon now)",
                                     lineterm="", n=1))


def same_values(a: Any, b: Any, path: str = "") -> list[str]:
    """Where two messages' values differ: floats to 1e-9 relative (NaN equals NaN)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{path}: keys differ: {sorted(set(a) ^ set(b))}"]
        return [d for k in a for d in same_values(a[k], b[k], f"{path}.{k}")]
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            return [f"{path}: length {len(a)} != {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in same_values(x, y, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, (int, float)) and not isinstance(b, bool) \
            or isinstance(b, float) and isinstance(a, (int, float)) and not isinstance(a, bool):
        ok = (a != a and b != b) or math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-24)
        return [] if ok else [f"{path}: {a!r} != {b!r}"]
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


def _contact_parts(line: str) -> tuple[str, Counter[str]]:
    """A contact line as its frame's fields (``t_sample``, ``unknown``: not the instant of
    the look ``t=`` nor the count ``n=``) and its contacts' texts without their track ids
    (an id counts the tracks born before: history, not this frame)."""
    head, *contacts = line.split(" | ")
    frame = " ".join(w for w in head.split()[1:] if not w.startswith(("t=", "n=")))
    return frame, Counter(" ".join(w for w in c.split() if not w.startswith("id=")) for c in contacts)


def _t_sample(line: str) -> str:
    return next(w for w in line.split() if w.startswith("t_sample="))


def published_diff(sc: Scenario, messages: list[tuple[str, dict[str, Any]]]) -> list[str]:
    """How the element and contact messages a running daemon published on the scenario's
    recording (in order) differ from the offline driver's, i.e. from ``NAME.chk``.

    The service and the offline driver are one daemon on the same reads, but when its
    contact loop looks is the event loop's (a replay as fast as possible skips frames): so
    the element messages must be the offline driver's one for one (every field but ``seq``
    and ``source``, floats to 1e-9) and render to the ``.chk``'s element lines; a contact
    message must render as the ``.chk``'s contact line of the same ``t_sample`` (the frame
    it estimated), leaving out the instant of the look, the track ids, and a contact one
    of them has not yet born or already ended (one at most); the last contact message (the
    drain's estimate of the last frame) must be the ``.chk``'s last contact line but for its
    track ids. Empty: no difference."""
    want = [ln for ln in expected(sc) if not ln.startswith("health")]
    mine = [(t, m) for t, m in messages if t in ("element", "contact")]
    offline, _ = offline_run(sc, paths(sc)[0])

    def elements(ms: list[tuple[str, dict[str, Any]]]) -> list[dict[str, Any]]:
        return [{k: v for k, v in m.items() if k not in ("seq", "source")} for t, m in ms if t == "element"]

    out = same_values(elements(mine), elements(offline), "element")[:20]
    got = [render(t, m) for t, m in mine]
    out += list(difflib.unified_diff([ln for ln in want if ln.startswith("element")],
                                     [ln for ln in got if ln.startswith("element")],
                                     f"{sc.name}.chk", "published", lineterm="", n=0))[:20]
    committed = {_t_sample(ln): ln for ln in want if ln.startswith("contact")}
    contacts = [ln for ln in got if ln.startswith("contact")]
    for ln in contacts:
        theirs = committed.get(_t_sample(ln))
        if theirs is None:  # a frame only the running daemon estimated
            continue
        (fa, a), (fb, b) = _contact_parts(ln), _contact_parts(theirs)
        if fa != fb:
            out.append(f"contact {_t_sample(ln)}: {fa!r} != {fb!r} (committed)")
        if sum(((a - b) + (b - a)).values()) > 1:
            out.append(f"contact {_t_sample(ln)}: {sorted(a - b)} != {sorted(b - a)} (committed)")
    last = [ln for ln in want if ln.startswith("contact")][-1:]
    if [(ln.split(" | ")[0], _contact_parts(ln)[1]) for ln in contacts[-1:]] != \
            [(ln.split(" | ")[0], _contact_parts(ln)[1]) for ln in last]:
        out.append(f"last contact: {contacts[-1:]!r} != {last!r} (committed)")
    return out


def write_readme() -> None:
    lines = ["# Golden recordings", "",
             "MCAP recordings of the virtual mesh's gateway lines (the `serial` channel, as",
             "`cellbridge record --serial` keeps them), a link's capture file (`.cbcap`) of hand-crafted",
             "frames, and, in `NAME.chk`, the daemon's output on each, one line per message.",
             "Made by `tests/support/golden_corpus.py` (virtual mesh seed 1, host time",
             f"{T0:.0f} at virtual time 0, reads batched per {READ_GRAIN * 1e3:g} ms);",
             "`tests/test_golden_corpus.py` replays them all; the replay tests run the real daemon on",
             "`daemon_press.cbcap` with `daemon_press.toml` and check what it publishes against `daemon_press.chk`.", "",
             "- `.venv/bin/python tests/support/golden_corpus.py --regen`: the daemon's output changed on purpose;",
             "  rewrite the `.chk` files, review `git diff tests/data/golden`, commit with the change.",
             "- `.venv/bin/python tests/support/golden_corpus.py --remake`: the emulator changed; make the",
             "  recordings again (and the `.chk` files).",
             "- `.venv/bin/python tests/support/golden_corpus.py --diff`: show what would change.",
             "- `.venv/bin/cellbridge decode NAME.mcap --run --topics contact,element`: each read's frames",
             "  followed by the messages the daemon makes of it (with the default config; the corpus's",
             "  own settings are in `tests/support/golden_corpus.py`).", "",
             "| recording | how it was made |", "|---|---|"]
    lines += [f"| `{paths(sc)[0].name}` | {sc.note} ({sc.seconds:g} s) |" for sc in SCENARIOS]
    (DATA / "README.md").write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--regen", action="store_true", help="rewrite the .chk files from the committed recordings")
    ap.add_argument("--remake", action="store_true", help="run the virtual mesh again: recordings and .chk files")
    ap.add_argument("--diff", action="store_true", help="print what would change, change nothing")
    ap.add_argument("only", nargs="*", help="scenario names (default: all)")
    args = ap.parse_args(argv)
    chosen = [sc for sc in SCENARIOS if not args.only or sc.name in args.only]
    DATA.mkdir(parents=True, exist_ok=True)
    changed = 0
    for sc in chosen:
        mcap, chk = paths(sc)
        if args.remake:
            make_recording(sc, mcap)
        got = daemon_output(sc, mcap)
        if args.diff:
            d = diff(sc, got) if chk.exists() else [f"(no {chk.name} yet)"]
            changed += bool(d)
            print("\n".join(d) if d else f"{sc.name}: unchanged")
        elif args.regen or args.remake:
            chk.write_text("\n".join(got) + "\n")
            print(f"{sc.name}: {mcap.stat().st_size} bytes of recording, {len(got)} lines of output")
    if args.remake:
        write_readme()
    if not (args.regen or args.remake or args.diff):
        ap.print_help()
        return 2
    return 1 if changed else 0


if __name__ == "__main__":
    sys.exit(main())

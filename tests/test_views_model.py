"""The views' sans-I/O core: the skin view model, the terminal grid layout, the page's JSON,
the Foxglove messages, and the shells' refusals of bad options."""

from __future__ import annotations

import json
import math
import struct
import subprocess
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellbridge.views import foxglove as fx
from cellbridge.views import textgrid
from cellbridge.views.model import SkinView, contact_line, level_rgb
from cellbridge.views.web import frame_json, is_loopback_host
from daemon_harness import CLI

LAYOUT = {"layout": {"side": 0.04, "ids": [1, 2, 3, 4], "x": [0.02, 0.06, 0.02, 0.06], "y": [0.02, 0.02, 0.06, 0.06]}}


def element(seq: int, force: dict[int, float], dc1: float = 0.0, status: int = 2) -> dict:
    ids = [1, 2, 3, 4]
    return {"v": 1, "seq": seq, "bridge": ids, "force": [force.get(b, math.nan) for b in ids],
            "valid": [b in force for b in ids], "touched": [b in force for b in ids],
            "status": [0 if b in force else status for b in ids], "dc1": [dc1] * 4, "dc2": [dc1] * 4,
            "area": [1e-4] * 4, "t_sample": [100.0 + seq] * 4, "future_field": [{"x": 1}] * 4}


def contact(seq: int, **kw: object) -> dict:
    c = {"id": 7, "x": 0.045, "y": 0.031, "force": 2.5, "diameter": 0.012, "observable": [True, False],
         "valid": True, "missed": 0, "sigma_x": 1e-4, "sigma_y": 0.004, "elements": [2, 4], "new_thing": {"a": 1}}
    c.update(kw)
    return {"v": 1, "seq": seq, "t_sample": 1.0, "contacts": [c]}


def fed() -> SkinView:
    m = SkinView(force_scale=5.0)
    m.feed("topology", dict(LAYOUT, seq=0), 0.0)
    m.feed("element", element(0, {2: 2.5}), 0.0)
    m.feed("contact", contact(0), 0.0)
    return m


def test_the_pressed_element_and_the_contact_land_where_the_layout_puts_them() -> None:
    f = fed().frame(0.0)
    assert (f.rows, f.cols) == (2, 2) and f.quantity == "force"
    cell = {c.bridge: c for c in f.cells}
    assert (cell[2].row, cell[2].col) == (0, 1) and (cell[3].row, cell[3].col) == (1, 0)
    assert cell[2].label == "2.5N" and cell[2].level == pytest.approx(0.5) and cell[1].label == ""
    (c,) = f.contacts
    assert (c.col, c.row) == pytest.approx((0.045 / 0.04, 0.031 / 0.04)) and c.diameter == pytest.approx(0.3)
    assert c.line.startswith("#7  x 45.0 mm  y ~31.0 ±4 mm (unresolved)  F 2.50 N  ⌀ 12.0 mm")


def test_an_element_without_a_force_shows_its_dc_or_that_it_is_calibrating() -> None:
    m = SkinView(dc_scale=2.0)
    m.feed("topology", LAYOUT, 0.0)
    m.feed("element", element(0, {}, dc1=1e-12, status=8), 0.0)  # ambiguous: a light touch
    f = m.frame(0.0)
    assert f.quantity == "dc" and all(c.label == "1.0pF" and c.level == pytest.approx(0.5) for c in f.cells)
    m.feed("element", element(1, {3: 1.0}, dc1=math.nan, status=1), 0.0)  # baseline being taken
    f = m.frame(0.0)
    assert f.quantity == "force" and [c.label for c in f.cells] == ["cal", "cal", "1.0N", "cal"]
    assert math.isnan(f.cells[0].level)


def test_gaps_in_seq_are_counted_as_this_views_losses_and_a_restart_is_noticed() -> None:
    m = fed()
    m.feed("element", element(5, {2: 1.0}), 0.1)  # 1..4 lost
    m.feed("health", {"v": 1, "seq": 10}, 0.1)
    m.feed("health", {"v": 1, "seq": 0}, 0.2)  # a new daemon
    assert m.lost == {"element": 4} and m.daemon_restarts == 1 and m.needs_topology


def test_a_silent_daemon_is_shown_as_such() -> None:
    m = fed()
    assert m.live(1.0) and not m.live(10.0)
    assert "SILENT" in m.frame(10.0).status[0]


payloads = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5)
                        | st.binary(max_size=5), lambda c: st.lists(c, max_size=4)
                        | st.dictionaries(st.sampled_from(["bridge", "force", "contacts", "id", "x", "layout", "ids",
                                                           "seq", "links", "bridges", "observable", "status"]), c,
                                          max_size=6), max_leaves=20)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["element", "contact", "health", "topology", "raw"]), payloads), max_size=8))
def test_no_payload_makes_the_model_raise(messages: list) -> None:
    m = fed()
    for topic, payload in messages:
        m.feed(topic, payload, 0.0)
    f = m.frame(0.0)
    json.dumps(frame_json(f), allow_nan=False)  # the page's JSON stays strict
    textgrid.layout(f, 80, 14)


def test_the_terminal_grid_puts_y_up_and_marks_the_contact_inside_its_element() -> None:
    g = textgrid.layout(fed().frame(0.0), 40, 8)
    cw, ch = g.cw, g.ch
    text = g.text()
    assert len(text) == 2 * ch and len(text[0]) == 2 * cw
    bottom = "\n".join(text[ch:])
    assert "2.5N" in bottom  # bridge 2 is in the bottom row (y up)
    row = next(i for i, line in enumerate(text) if "↕7" in line)  # y unresolved: ↕
    col = text[row].index("↕7")
    # inside bridge 2's element, within a character of its estimated place (moved off the id "2")
    assert cw <= col < 2 * cw and ch <= row < 2 * ch
    assert abs(col - int(0.045 / 0.04 * cw)) <= 1 and row == int((2 - 0.031 / 0.04) * ch)


def _words_beside(line: str, start: int, n: int) -> tuple[str, str]:
    return line[start - 1: start] if start > 0 else " ", line[start + n: start + n + 1] or " "


@pytest.mark.parametrize("x, y", [(0.045, 0.031), (0.041, 0.028), (0.049, 0.0345), (0.021, 0.055), (0.06, 0.03)])
def test_a_contact_marker_never_runs_into_an_elements_id_or_label(x: float, y: float) -> None:
    """In 80×24 the marker ``↕0`` landed just before an element's label: ``↕02.1N`` read as
    one word. The marker keeps a blank on each side, in the element it belongs to."""
    m = SkinView()
    m.feed("topology", LAYOUT, 0.0)
    m.feed("element", element(0, {1: 2.1, 2: 2.1, 3: 2.1, 4: 2.1}), 0.0)
    m.feed("contact", {"v": 1, "seq": 0, "contacts": [{"id": 0, "x": x, "y": y, "force": 2.0, "diameter": 0.01,
                                                        "observable": [True, False]}]}, 0.0)
    for width, height in ((80, 14), (40, 8), (30, 6), (24, 4)):
        g = textgrid.layout(m.frame(0.0), width, height)
        text = g.text()
        row = next(i for i, line in enumerate(text) if "↕0" in line)
        col = text[row].index("↕0")
        assert _words_beside(text[row], col, 2) == (" ", " "), (width, height, text[row])
        want_col, want_row = int(x / 0.04 * g.cw), int((2 - y / 0.04) * g.ch)
        assert abs(col - want_col) / g.cw <= 0.5 and abs(row - want_row) / g.ch <= 0.5, (col, row, want_col, want_row)


def test_a_skin_larger_than_the_terminal_keeps_readable_cells() -> None:
    m = SkinView()
    ids = list(range(1, 257))
    m.feed("topology", {"layout": {"side": 0.04, "ids": ids, "x": [0.02 + 0.04 * ((i - 1) % 16) for i in ids],
                                   "y": [0.02 + 0.04 * ((i - 1) // 16) for i in ids]}}, 0.0)
    g = textgrid.layout(m.frame(0.0), 80, 14)
    assert (g.cw, g.ch) == (5, 1) and len(g.rows[0]) == 80 and len(g.rows) == 16  # 16 > 14 rows: it scrolls
    g = textgrid.layout(m.frame(0.0), 40, 10)
    assert (g.cw, g.ch) == (textgrid.MIN_W, textgrid.MIN_H) and len(g.rows[0]) == 64  # never below 4x1: scrolls


def test_colour_ramp_runs_from_dark_to_red_and_is_grey_for_unknown() -> None:
    assert level_rgb(math.nan) == (90, 90, 90)
    assert sum(level_rgb(0.0)) < 150 and level_rgb(1.0) == (220, 30, 30) and level_rgb(7.0) == level_rgb(1.0)
    brightness = [sum(level_rgb(v / 10)) for v in range(0, 7)]
    assert brightness == sorted(brightness)  # more force, brighter, up to yellow


def test_contact_line_says_when_a_contact_has_no_pressure() -> None:
    m = fed()
    m.feed("contact", contact(1, valid=False, missed=2), 0.0)
    assert contact_line(m.contacts[0]).endswith("(no pressure: position only)  (missed 2)")


def test_foxglove_grid_holds_each_elements_force_at_its_cell() -> None:
    f = fed().frame(0.0)
    values = struct.unpack("<8f", fx.grid_bytes(f))
    forces = values[0::2]
    assert forces[1] == pytest.approx(2.5) and forces[0] == 0.0 and forces[2] == 0.0  # bridge 2: row 0, col 1
    grid = fx.make_grid(f, 1_000_000_123)
    assert grid.encode()  # the SDK accepts it


def test_foxglove_scene_has_one_disk_per_contact_after_clearing_the_old_ones() -> None:
    model = fed()
    scene = fx.make_scene(model, model.frame(0.0), {}, False, 5)
    assert scene.encode()


def test_the_committed_foxglove_layout_is_the_one_the_command_writes(tmp_path: Path) -> None:
    out = tmp_path / "layout.json"
    r = subprocess.run([CLI, "foxglove", "--write-layout", str(out)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    committed = Path(__file__).parent.parent / "docs" / "foxglove-layout.json"
    assert json.loads(out.read_text()) == json.loads(committed.read_text())
    text = committed.read_text()
    for topic in fx.TOPICS.values():  # but transforms: the 3D panel takes them from every topic that has them
        assert topic in text or topic == fx.TOPICS["tf"], topic


def test_loopback_hosts() -> None:
    assert is_loopback_host("127.0.0.1") and is_loopback_host("::1") and is_loopback_host("localhost")
    assert not is_loopback_host("0.0.0.0") and not is_loopback_host("192.168.1.2") and not is_loopback_host("eth0")


@pytest.mark.parametrize("argv, said", [
    (["web", "--host", "0.0.0.0"], "refusing to serve on 0.0.0.0"),
    (["web", "--max-rate", "0"], "--max-rate must be within"),
    (["foxglove", "--host", "0.0.0.0"], "refusing to listen on 0.0.0.0"),
    (["watch", "--server-key", "x.key"], "--server-key and --client-key go together"),
    (["watch"], "needs a terminal"),
])
def test_bad_options_are_refused_with_a_reason(argv: list[str], said: str) -> None:
    r = subprocess.run([CLI, *argv], capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert r.returncode == 2 and said in r.stderr, r.stderr


def test_a_short_token_is_refused(tmp_path: Path) -> None:
    (tmp_path / "t").write_text("short\n")
    r = subprocess.run([CLI, "web", "--host", "0.0.0.0", "--token-file", str(tmp_path / "t")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "at least 16 characters" in r.stderr


# ---- hostile payloads: the model never raises, stays bounded, shows text escaped -----------

def test_a_health_with_an_infinite_drop_count_is_shown_not_raised() -> None:
    """pub.dropped.element = inf raised OverflowError out of feed(): the page froze, foxglove died."""
    m = fed()
    m.feed("health", {"v": 1, "seq": 1, "uptime": 1e308, "pub": {"dropped": {"element": math.inf, "contact": 3}},
                      "bridges": {"1": {"lost": 1e308, "frames": 1e308, "sample_rate": math.inf},
                                  "2": {"lost": 1e308, "frames": 5, "sample_rate": 1e308}},
                      "contact_estimation": {"last_ms": -math.inf, "max_ms": math.nan}}, 0.0)
    assert m.health_count == 1 and m.malformed == 0
    status = "\n".join(m.frame(0.0).status)
    assert "uptime 1e+308 s" in status and "daemon dropped ?" in status and "rate ? samples/s" in status
    assert "loss ? %" in status
    assert max(len(line) for line in status.splitlines()) < 200


def test_a_layout_spanning_1e308_is_drawn_unplaced_and_said_so() -> None:
    """A topology whose x spans ±1e308 raised OverflowError out of frame()."""
    m = SkinView()
    m.feed("topology", {"layout": {"side": 0.04, "ids": [1, 2, 3], "x": [-1e308, 1e308, 0.0], "y": [0.0, 0.0, 1e300]}},
           0.0)
    m.feed("element", element(0, {1: 1.0}), 0.0)
    f = m.frame(0.0)
    assert {c.bridge for c in f.cells} == {1, 2, 3, 4}  # 1 and 2 are not where they say: unplaced, still shown
    json.dumps(frame_json(f), allow_nan=False)
    fx.grid_bytes(f)
    textgrid.layout(f, 80, 14)


def test_a_tiny_side_never_makes_a_huge_grid() -> None:
    """Two elements 1 m apart with a 0.2 mm side made a 5001 × 5001 grid (2.3 GB of lists per
    Foxglove frame). The grid is at most MAX_GRID a side; beyond, elements are shown unplaced
    and a status line says why."""
    MAX_GRID = 128  # cellbridge.views.model.MAX_GRID, as docs/views.md says

    m = SkinView()
    m.feed("topology", {"layout": {"side": 0.0002, "ids": [1, 2], "x": [0.0, 1.0], "y": [0.0, 1.0]}}, 0.0)
    f = m.frame(0.0)
    assert f.rows * f.cols <= 2 * MAX_GRID and len(f.cells) == 2
    assert any("beyond the 128 x 128 drawn" in line and "5001 x 5001" in line for line in f.status), f.status
    assert len(fx.grid_bytes(f)) == 8 * f.rows * f.cols
    # a layout that fits is drawn to scale, up to MAX_GRID a side
    m.feed("topology", {"layout": {"side": 0.001, "ids": [1, 2], "x": [0.0, (MAX_GRID - 1) * 0.001], "y": [0.0, 0.0]}},
           0.0)
    f = m.frame(0.0)
    assert (f.rows, f.cols) == (1, MAX_GRID) and not any("beyond" in line for line in f.status)


def test_kept_state_is_bounded_whatever_the_payloads_say() -> None:
    MAX_ELEMENTS, MAX_CONTACTS, HISTORY_BUDGET = 4096, 64, 256_000  # as docs/views.md says
    m = SkinView()
    n = 3 * MAX_ELEMENTS
    m.feed("element", {"seq": 0, "bridge": list(range(n)), "force": [1.0] * n, "valid": [True] * n}, 0.0)
    for seq in range(1, 5):
        m.feed("element", {"seq": seq, "bridge": list(range(n)), "force": [1.0] * n, "valid": [True] * n,
                           "t_sample": [float(seq)] * n}, 0.0)
    m.feed("contact", {"seq": 0, "contacts": [{"id": i, "x": 0.0, "y": 0.0, "elements": list(range(10_000))}
                                              for i in range(1000)]}, 0.0)
    assert len(m.elements) == MAX_ELEMENTS and len(m.contacts) == MAX_CONTACTS
    assert all(len(c.elements) <= MAX_CONTACTS for c in m.contacts)
    assert sum(e.history.maxlen or 0 for e in m.elements.values()) <= 2 * HISTORY_BUDGET
    assert m.not_kept == 5 * (n - MAX_ELEMENTS) + 1000 - MAX_CONTACTS
    f = m.frame(0.0)
    assert f.rows * f.cols <= MAX_ELEMENTS * 2 and "beyond limits" in f.status[-1]


def test_control_characters_from_the_daemon_are_shown_escaped() -> None:
    """Link names, calibration status and a tare error reached the terminal raw (an OSC 52
    clipboard write, a CSI colour)."""
    osc52 = "\x1b]52;c;cHduZWQ=\x07"
    m = fed()
    m.feed("health", {"v": 1, "seq": 1, "links": {osc52: {"connected": True}, "gw\x9b31m": {"connected": False}},
                      "layout": {"calibration": {"ready": "\x1b[2J", "collecting": "\u202e9"}}}, 0.0)
    text = "\n".join(m.frame(0.0).status)
    assert not any(ord(c) < 0x20 and c != "\n" or 0x7f <= ord(c) < 0xa0 or c == "\u202e" for c in text), repr(text)
    assert "\\x1b]52;c;cHduZWQ=\\x07:up" in text and "gw\\x9b31m:DOWN" in text and "\\x1b[2J ready" in text
    from cellbridge.views.model import printable

    assert printable("a\x00b\u2028c\U000e0001") == "a\\x00b\\u2028c\\U000e0001"
    assert printable("x" * 100, 10) == "x" * 10 + "…" and printable(b"\x1b") == "<bytes>"


def test_one_picture_shows_one_source() -> None:
    """Two daemons behind one proxy: the view shows the source asked for, or the first heard,
    and counts the other's messages without drawing them."""
    def stream(m: SkinView) -> None:
        for seq, (src, f) in enumerate([("robot:5560", 1.0), ("robot:5562", 4.0), ("robot:5560", 1.5),
                                        ("robot:5562", 4.5)]):
            m.feed("topology", dict(LAYOUT, source=src, seq=seq // 2), 0.0)
            m.feed("element", dict(element(seq // 2, {2: f}), source=src), 0.0)
            m.feed("contact", dict(contact(seq // 2, force=f), source=src), 0.0)
            m.feed("health", {"v": 1, "seq": seq // 2, "uptime": f, "source": src}, 0.0)

    first, picked = SkinView(), SkinView(source="robot:5562")
    stream(first)
    stream(picked)
    assert {c.bridge: c.force for c in first.frame(0.0).cells}[2] == 1.5 and first.contacts[0].force == 1.5
    assert {c.bridge: c.force for c in picked.frame(0.0).cells}[2] == 4.5 and picked.contacts[0].force == 4.5
    assert first.lost == {} and picked.lost == {} and first.daemon_restarts == picked.daemon_restarts == 0
    assert first.other_sources == {"robot:5562": 8} and picked.other_sources == {"robot:5560": 8}
    assert any("source: robot:5560 (the first heard); not shown: robot:5562 (8)" in s for s in first.frame(0.0).status)
    nobody = SkinView(source="elsewhere")
    stream(nobody)
    assert not nobody.elements and "waiting for the first message of source elsewhere" in nobody.frame(0.0).status[0]


def test_the_daemons_default_source_differs_between_two_daemons_on_one_host() -> None:
    """Both defaulted to the host name: behind one proxy their streams could not be told apart."""
    import socket

    import zmq.asyncio
    from cellbridge.daemon.shell.publisher import Publisher

    ctx = zmq.asyncio.Context()
    try:
        a = Publisher(ctx, "tcp://127.0.0.1:5560", 10)
        b = Publisher(ctx, "tcp://127.0.0.1:5562", 10)
        c = Publisher(ctx, "ipc:///run/cellbridge/pub", 10)
        named = Publisher(ctx, "tcp://127.0.0.1:5564", 10, source="left-arm")
        host = socket.gethostname()
        assert (a.source, b.source, c.source) == (f"{host}:5560", f"{host}:5562", f"{host}:ipc:///run/cellbridge/pub")
        assert named.source == "left-arm"
        for p in (a, b, c, named):
            p.close()
    finally:
        ctx.term()

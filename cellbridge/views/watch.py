"""``cellbridge watch``: the skin in a terminal, over SSH too (Textual).

A full-screen view of what the daemon publishes: the element grid coloured by force
(by ΔC1 while no element has a force yet, e.g. before calibration ends), each contact
marked at its estimated position with its id, a line per contact (position, force,
diameter; an axis the readings do not determine is shown as unresolved), and the
mesh's health. Drawing happens at most ``--fps`` times a second on the newest state,
whatever the rate of the skin; messages are all read (and counted) in between.

Nothing the daemon sends reaches the terminal as it is: every string is shown with its
control characters escaped (:func:`~cellbridge.views.model.printable`), so a link name
holding an escape sequence cannot write to the clipboard or recolour the terminal.
SIGTERM, SIGHUP and Ctrl-C end the view as ``q`` does (the terminal restored); a stop
that hangs is cut off after a deadline, the terminal's modes and screen put back by hand
(:mod:`cellbridge.views.signals`).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
import termios
import time
from collections.abc import Callable
from typing import Any

from cellbridge.daemon.shell.subscribe import QUIET_S
from cellbridge.views.model import SkinView, printable
from cellbridge.views.signals import ignore_stop_signals, on_stop_signal, write_now
from cellbridge.views.source import Source, add_source_arguments, open_source

KEYS = "q quit  p pause  t tare  +/- force scale"


def shown(text: str) -> str:
    """Text as written to the terminal: every line through :func:`printable` (the model's
    lines are already; this is the last gate before the screen)."""
    return "\n".join(printable(line, 100_000) for line in text.split("\n"))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "A full-screen terminal view of a running daemon: the skin's elements coloured by\n"
        "force, each contact at its estimated position (finer than an element) with its\n"
        "id, force and diameter, and the mesh's health. Works over SSH in 80x24; a larger\n"
        "skin scrolls (arrow keys / mouse wheel). A skin on a robot (a daemon whose [layout]\n"
        "file is a skin description) is drawn patch by patch, titled by link and name.\n\n"
        "keys:\n"
        "  q        quit (also Ctrl-C)\n"
        "  p        pause the display (messages are still read and counted)\n"
        "  t        tare: re-take every element's baseline (asks for confirmation: y / n;\n"
        "           a replay has no control socket: there the tare says it was not sent)\n"
        "  + / -    force at full colour /2 / x2 (more / less sensitive)\n\n"
        "examples:\n"
        "  cellbridge watch\n"
        "  ssh robot -t cellbridge watch\n"
        "  cellbridge watch --endpoint tcp://robot:5560 --control tcp://robot:5561 \\\n"
        "      --server-key server.key --client-key me.key_secret"
    )
    add_source_arguments(parser)
    parser.add_argument("--fps", type=float, default=30.0,
                        help="most screen refreshes a second (default: 30)")


def run(args: argparse.Namespace) -> int:
    problem = None
    if not 1 <= args.fps <= 120:
        problem = f"--fps must be within 1..120, got {args.fps}"
    elif not sys.stdout.isatty():
        problem = "needs a terminal (for JSON lines use 'cellbridge sub')"
    source = open_source("watch", args, problem)
    if source is None:
        return 2
    try:
        model = SkinView(force_scale=args.force_scale, source=args.source, endpoint=args.endpoint, quiet_after=QUIET_S)
        app = _make_app(source, model, args.fps, args.endpoint, _terminal_restorer())
        app.run()
    except KeyboardInterrupt:
        pass
    finally:
        ignore_stop_signals()
        source.close()
    return 0


# Leave the alternate screen, show the cursor, stop mouse reports and bracketed paste: what a
# terminal needs back when the view cannot end its own way.
_RESET_SCREEN = b"\x1b[?1000l\x1b[?1002l\x1b[?1003l\x1b[?1006l\x1b[?1015l\x1b[?2004l\x1b[?25h\x1b[?1049l"


def _terminal_restorer() -> Callable[[], None]:
    """What puts this terminal back as it is now (its modes, and the screen) if a stop hangs."""
    try:
        saved: list[Any] | None = termios.tcgetattr(sys.stdin.fileno())
    except (termios.error, OSError, ValueError):
        saved = None

    def restore() -> None:
        if saved is not None:
            with contextlib.suppress(termios.error, OSError, ValueError):
                termios.tcsetattr(sys.stdin.fileno(), termios.TCSANOW, saved)
        write_now("/dev/tty", _RESET_SCREEN)

    return restore


def _make_app(source: Source, model: SkinView, fps: float, endpoint: str, restore: Callable[[], None]) -> Any:
    # Textual is imported here so that `cellbridge --help` stays fast.
    from rich.segment import Segment
    from rich.style import Style
    from rich.text import Text
    from textual.app import App, ComposeResult
    from textual.binding import Binding
    from textual.containers import ScrollableContainer
    from textual.geometry import Region
    from textual.screen import ModalScreen
    from textual.strip import Strip
    from textual.widget import Widget
    from textual.widgets import Static

    from cellbridge.views import textgrid

    styles: dict[tuple[Any, Any], Style] = {}

    def style(fg: tuple[int, int, int], bg: tuple[int, int, int]) -> Style:
        st = styles.get((fg, bg))
        if st is None:
            st = styles[(fg, bg)] = Style(color=f"rgb({fg[0]},{fg[1]},{fg[2]})", bgcolor=f"rgb({bg[0]},{bg[1]},{bg[2]})")
        return st

    class SkinGrid(Widget):
        """The element grid. Only rows that changed are repainted: over a slow link a
        refresh costs what changed on the skin, not the whole screen."""

        def __init__(self) -> None:
            super().__init__()
            self.lines: list[list[Segment]] = []

        def show(self, grid: textgrid.TextGrid) -> None:
            lines = []
            for row in grid.rows:  # runs of one colour pair as one segment
                segs: list[Segment] = []
                run, key = "", None
                for ch, fg, bg in row:
                    if (fg, bg) != key and run:
                        segs.append(Segment(run, style(*key)))  # type: ignore[misc]  # key is set whenever run is not empty
                        run = ""
                    key = (fg, bg)
                    run += ch
                if run:
                    segs.append(Segment(run, style(*key)))  # type: ignore[misc]  # key is set whenever run is not empty
                lines.append(segs)
            width = len(grid.rows[0]) if grid.rows else 0
            old = self.lines
            self.lines = lines
            if len(old) != len(lines) or self.styles.width is None or self.styles.width.value != width:
                self.styles.width, self.styles.height = width, len(lines)
                self.refresh()
                return
            for y, (a, b) in enumerate(zip(old, lines)):
                if a != b:
                    self.refresh(Region(0, y, width, 1))

        def render_line(self, y: int) -> Strip:
            if y < len(self.lines):
                return Strip(self.lines[y])
            return Strip.blank(self.size.width)

    class ConfirmTare(ModalScreen[bool]):
        BINDINGS = [("y", "answer(True)", "yes"), ("n", "answer(False)", "no"), ("escape", "answer(False)", "no")]
        DEFAULT_CSS = "ConfirmTare { align: center middle; } ConfirmTare > Static { width: 60; border: heavy red; padding: 1 2; }"

        def compose(self) -> ComposeResult:
            yield Static("Tare: re-take the baseline of every element?\n"
                         "Press nothing on the skin meanwhile.\n\n  y  tare      n  cancel")

        def action_answer(self, yes: bool) -> None:
            self.dismiss(yes)

    class WatchApp(App[None]):
        TITLE = "cellbridge watch"
        CSS = """
        Screen { layout: vertical; }
        #head { height: 1; background: $primary-background; }
        #skin { height: 1fr; }
        #empty { height: auto; }
        #contacts { height: auto; max-height: 4; }
        #status { height: auto; color: $text-muted; }
        #keys { height: 1; background: $primary-background; }
        """
        BINDINGS = [("q", "quit", "quit"), Binding("ctrl+c", "quit", "quit", priority=True),
                    ("p", "pause", "pause"), ("t", "tare", "tare"),
                    ("plus", "scale(0.5)", ""), ("equals_sign", "scale(0.5)", ""), ("minus", "scale(2.0)", "")]

        def compose(self) -> ComposeResult:
            yield Static(shown(f"cellbridge watch  {endpoint}"), id="head")
            with ScrollableContainer(id="skin"):
                yield SkinGrid()
            yield Static(id="empty")
            yield Static(id="contacts")
            yield Static(id="status")
            yield Static(KEYS, id="keys")

        def on_mount(self) -> None:
            self.set_interval(1.0 / fps, self.tick)
            self._shown_live: bool | None = None
            self.errors = 0
            loop = asyncio.get_running_loop()
            on_stop_signal(lambda: loop.call_soon_threadsafe(self.exit),  # as q: the terminal restored
                           restore=restore)  # by hand, if that stop hangs

        def tick(self) -> None:
            try:
                source.drain(model)
                now = time.monotonic()
                live = model.live(now)
                if model.paused or not (model.changed or live != self._shown_live or not live):
                    return
                self._shown_live = live
                self.draw(now)
            except Exception:  # the model never raises on a payload; should anything else, count it and go on
                self.errors += 1

        def draw(self, now: float) -> None:
            frame = model.frame(now)
            box = self.query_one("#skin").size
            width, height = (box.width, box.height) if box.width else (self.size.width, max(4, self.size.height - 10))
            self.query_one(SkinGrid).show(textgrid.layout(frame, width, height))
            self.set_text("#empty", "" if frame.cells else
                          "no elements yet (waiting for the daemon's layout and readings)")
            what = "force" if frame.quantity == "force" else "ΔC1 (no force yet)"
            self.set_text("#contacts", "\n".join([c.line for c in frame.contacts] or ["no contact"]))
            status = list(frame.status)
            status.append(f"colour: {what}, full at {frame.scale:g} {'N' if frame.quantity == 'force' else 'pF'}"
                          + (f"   view errors {self.errors}" if self.errors else ""))
            if source.notice:  # a line of its own: a tare's answer is read whole, not cut at 80 columns
                status.append(source.notice)
            self.set_text("#status", "\n".join(status))

        def set_text(self, selector: str, text: str) -> None:
            """Update a text area only when its text changed (no repaint for nothing)."""
            widget = self.query_one(selector, Static)
            if getattr(widget, "_shown", None) != text:
                widget._shown = text  # type: ignore[attr-defined]  # a marker attribute of our own on the widget
                widget.update(Text(shown(text), no_wrap=True, overflow="ellipsis"))

        def action_pause(self) -> None:
            model.paused = not model.paused
            self.draw(time.monotonic())

        def action_scale(self, factor: float) -> None:
            model.scale(factor)
            self.draw(time.monotonic())

        def action_tare(self) -> None:
            def answered(yes: bool | None) -> None:
                if yes:
                    source.tare()
                else:
                    source.notice = "tare: cancelled"
                self.draw(time.monotonic())
            self.push_screen(ConfirmTare(), answered)

    return WatchApp()

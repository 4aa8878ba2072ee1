"""``cellbridge info FILE.mcap``: what a recording holds, at a glance.

Topics with their message counts, the time span, the daemons (``source``), the bridges
seen (in element, raw and health messages), the contacts seen (distinct tracked contact
ids, most at once, strongest force) and the links whose bytes were kept. A recording
cut short (recorder killed) is summarised up to its last whole chunk and says so.
A damaged recording is summarised from every part that can be read, and ``info`` then
says on one line what was skipped and exits 1. :class:`Summary` is the core (fed decoded
messages, of any shape: a field of the wrong type is left out, never a crash); ``run``
reads and prints.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from collections import Counter
from pathlib import Path
from typing import Any

from cellbridge.recording.mcapfile import NotARecording, ReadResult, read_payloads

#: Distinct daemons (``source``) and serial links kept by name; more are counted, not named
#: (a damaged file could otherwise name millions). Names are cut to NAME_CHARS characters.
MAX_NAMES = 64
NAME_CHARS = 120
MAX_BRIDGE = 0xFFFF


def _name(v: Any) -> str | None:
    return v[:NAME_CHARS] if isinstance(v, str) else None


def _bridge(v: Any) -> int | None:
    """A bridge id as recorded (an int, or the decimal string of a JSON map key), or None."""
    if isinstance(v, str) and v.isdigit() and len(v) <= 5:
        v = int(v)
    return v if isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= MAX_BRIDGE else None


class Summary:
    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self.sources: set[str] = set()
        self.bridges: set[int] = set()
        self.contact_ids: set[int] = set()
        self.max_contacts = 0
        self.max_force = 0.0
        self.serial_links: Counter[str] = Counter()
        self.serial_bytes = 0
        self.more_names = 0  # sources and links not kept by name (over MAX_NAMES)

    def add(self, topic: str, payload: dict[str, Any], log_ns: int) -> None:
        """One decoded message. Any payload map is taken: fields of another type than the API
        gives them are not counted (a damaged or hand-made file)."""
        self.counts[topic] += 1
        self.first_ns = log_ns if self.first_ns is None else min(self.first_ns, log_ns)
        self.last_ns = log_ns if self.last_ns is None else max(self.last_ns, log_ns)
        source = _name(payload.get("source"))
        if source is not None and source not in self.sources:
            if len(self.sources) < MAX_NAMES:
                self.sources.add(source)
            else:
                self.more_names += 1
        if topic in ("element", "raw"):
            column = payload.get("bridge")
            if isinstance(column, list):
                self.bridges.update(b for b in map(_bridge, column) if b is not None)
        elif topic == "health":
            bridges = payload.get("bridges")
            if isinstance(bridges, dict):
                self.bridges.update(b for b in map(_bridge, bridges) if b is not None)
        elif topic == "contact":
            contacts = payload.get("contacts")
            if isinstance(contacts, list):
                self.max_contacts = max(self.max_contacts, len(contacts))
                for c in contacts:
                    if not isinstance(c, dict):
                        continue
                    cid = c.get("id")
                    if isinstance(cid, int) and not isinstance(cid, bool):
                        self.contact_ids.add(cid)
                    f = c.get("force")
                    if isinstance(f, float) and math.isfinite(f):
                        self.max_force = max(self.max_force, f)
        elif topic == "serial":
            link = _name(payload.get("link")) or "?"
            if link in self.serial_links or len(self.serial_links) < MAX_NAMES:
                self.serial_links[link] += 1
            else:
                self.more_names += 1
            data = payload.get("data")
            if isinstance(data, bytes):
                self.serial_bytes += len(data)

    def report(self) -> dict[str, Any]:
        duration = (self.last_ns - self.first_ns) * 1e-9 if self.first_ns is not None and self.last_ns else 0.0
        return {
            "topics": dict(sorted(self.counts.items())),
            "messages": sum(self.counts.values()),
            "start": self.first_ns * 1e-9 if self.first_ns is not None else None,
            "duration": duration,
            "sources": sorted(self.sources),
            "bridges": sorted(self.bridges),
            "contacts": {"distinct": len(self.contact_ids), "most_at_once": self.max_contacts,
                         "max_force": self.max_force},
            "serial": {"links": dict(self.serial_links), "bytes": self.serial_bytes},
            **({"names_not_kept": self.more_names} if self.more_names else {}),
        }


def summarise(path: Path) -> dict[str, Any]:
    """What :func:`format_text` prints, as a map. ``complete``: read through its footer;
    ``damaged``: the one-line account of what could not be read (absent when all could).
    NotARecording if it is not MCAP at all, OSError if it cannot be read."""
    s = Summary()
    result = ReadResult()
    for m, payload in read_payloads(path, result):
        s.add(m.topic, payload, m.log_ns)
    out = {"file": str(path), "bytes": path.stat().st_size, **s.report(), "complete": result.complete}
    if result.error:
        out["note"] = result.error
    if not result.ok:
        out["damaged"] = result.problem(path)
    return out


def format_text(info: dict[str, Any]) -> str:
    lines = [f"file:      {info['file']} ({info['bytes'] / 1e6:.2f} MB)"
             + ("" if info["complete"] else "  [cut short: read to its last whole chunk]")]
    lines.append(f"duration:  {info['duration']:.3f} s, {info['messages']} messages")
    lines.append("topics:    " + ", ".join(f"{t} {n}" for t, n in info["topics"].items()))
    lines.append("sources:   " + (", ".join(info["sources"]) or "-"))
    b = info["bridges"]
    lines.append(f"bridges:   {len(b)}" + (f" ({', '.join(map(str, b))})" if b else ""))
    c = info["contacts"]
    lines.append(f"contacts:  {c['distinct']} distinct, at most {c['most_at_once']} at once, "
                 f"strongest {c['max_force']:.2f} N")
    if info["serial"]["links"]:
        lines.append("serial:    " + ", ".join(f"{k} {n} reads" for k, n in info["serial"]["links"].items())
                     + f", {info['serial']['bytes']} bytes")
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Summarise a recording: topics and message counts, duration, daemons, bridges, "
                          "contacts seen, serial links kept. A recording cut short is read to its last whole "
                          "chunk (exit 0); a damaged one is summarised from what can be read, and a line on "
                          "stderr says what was skipped (exit 1). A file that is not there or cannot be read: exit 2.")
    parser.add_argument("files", type=Path, nargs="+", metavar="FILE.mcap")
    parser.add_argument("--json", action="store_true", help="one JSON object per file instead of text")


def run(args: argparse.Namespace) -> int:
    status = 0
    for path in args.files:
        try:
            info = summarise(path)
        except OSError as exc:  # not there, or not readable: 2, as decode, replay and robot score say it
            print(f"cellbridge info: {path}: {exc.strerror or exc}", file=sys.stderr)
            status = 2
            continue
        except NotARecording as exc:
            print(f"cellbridge info: {exc}", file=sys.stderr)
            status = max(status, 1)
            continue
        try:
            print(json.dumps(info) if args.json else format_text(info), flush=True)
        except BrokenPipeError:  # read by `head` and the like: the reader has what it wanted
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return status
        if "damaged" in info:
            print(f"cellbridge info: {info['damaged']}", file=sys.stderr, flush=True)
            status = max(status, 1)
    return status

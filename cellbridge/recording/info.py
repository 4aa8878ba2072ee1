"""``cellbridge info FILE.mcap``: what a recording holds, at a glance.

Topics with their message counts, the time span, the daemons (``source``), the bridges
seen (in element, raw and health messages), the contacts seen (distinct tracked contact
ids, most at once, strongest force) and the links whose bytes were kept. A recording
cut short (recorder killed) is summarised up to its last whole chunk and says so.
:class:`Summary` is the core (fed decoded messages); ``run`` reads and prints.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections import Counter
from pathlib import Path
from typing import Any

from cellbridge.recording import codec
from cellbridge.recording.mcapfile import ReadResult, read_messages


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

    def add(self, topic: str, payload: dict[str, Any], log_ns: int) -> None:
        self.counts[topic] += 1
        self.first_ns = log_ns if self.first_ns is None else min(self.first_ns, log_ns)
        self.last_ns = log_ns if self.last_ns is None else max(self.last_ns, log_ns)
        if isinstance(payload.get("source"), str):
            self.sources.add(payload["source"])
        if topic in ("element", "raw"):
            self.bridges.update(int(b) for b in payload.get("bridge", ()))
        elif topic == "health":
            self.bridges.update(int(b) for b in payload.get("bridges", {}))
        elif topic == "contact":
            contacts = payload.get("contacts", [])
            self.max_contacts = max(self.max_contacts, len(contacts))
            for c in contacts:
                self.contact_ids.add(c.get("id", -1))
                f = c.get("force")
                if isinstance(f, float) and f == f:
                    self.max_force = max(self.max_force, f)
        elif topic == "serial":
            self.serial_links[payload.get("link", "?")] += 1
            self.serial_bytes += len(payload.get("data", b""))

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
        }


def summarise(path: Path) -> dict[str, Any]:
    s = Summary()
    result = ReadResult()
    for m in read_messages(path, result):
        s.add(m.topic, codec.decode(m.topic, m.data), m.log_ns)
    out = {"file": str(path), "bytes": path.stat().st_size, **s.report(), "complete": result.complete}
    if result.error:
        out["note"] = result.error
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
                          "contacts seen, serial links kept.")
    parser.add_argument("files", type=Path, nargs="+", metavar="FILE.mcap")
    parser.add_argument("--json", action="store_true", help="one JSON object per file instead of text")


def run(args: argparse.Namespace) -> int:
    status = 0
    for path in args.files:
        try:
            info = summarise(path)
        except OSError as exc:
            print(f"cellbridge info: {path}: {exc.strerror or exc}", file=sys.stderr)
            status = 1
            continue
        except ValueError as exc:
            print(f"cellbridge info: {exc}", file=sys.stderr)
            status = 1
            continue
        try:
            print(json.dumps(info) if args.json else format_text(info), flush=True)
        except BrokenPipeError:  # read by `head` and the like: the reader has what it wanted
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return status
    return status

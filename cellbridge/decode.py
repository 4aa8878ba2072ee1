"""``cellbridge decode``: read a captured serial stream and print its frames.

For looking at what a gateway sends: a capture taken with e.g.
``cat /dev/ttyUSB0 > capture.bin`` or a hex dump pasted from a logic analyser. A
recording (``cellbridge record --serial``, or a golden corpus file) prints its lines'
frames interleaved with the daemon's messages, each read followed by what it caused:
what was recorded, or (``--run``) what the daemon makes of the reads now, offline and
deterministic. That is how a regression is read: the input beside the output it changed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from dataclasses import fields, is_dataclass
from typing import Any

from cellbridge.protocol import Frame, Reassembler, StreamDecoder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Decode a serial-line capture (COBS frames separated by 0x00) and print one JSON\n"
        "line per frame, fragments reassembled, then the drop counters on stderr.\n\n"
        "Fields are named as in docs/protocol.md. A DATA sample prints as\n"
        "[element, cycle, c1, c2, flags, index] (flags: 1, 2 counter of C1, C2 wrapped;\n"
        "4 no mesh time, index is then the bridge's own count; 8 held, event-based\n"
        "reporting), with the frame's sampling \"rate\" and \"period\" (cycles per sample;\n"
        "samples print unpacked, as absolute values, whatever the wire packed); a BEACON's\n"
        "\"time\" is null or {root, seq, time}; a HELLO has \"boots\". A READOUT (one skin\n"
        "frame \"index\" of every element routed through its sender) prints its \"samples\" as\n"
        "[bridge, c1, c2, flags] and the bridge ids \"unchanged\" and \"missing\"; a record in\n"
        "several frames prints a line per frame, numbered \"part\" of \"parts\", with the\n"
        "\"root\" whose mesh time its index counts. Frames of\n"
        "protocol versions 1 to 3 are read too and print with the fields they lack at their\n"
        "defaults (version 1: rate 0, flag 4, index 0, time null, boots 0; 1 and 2: period 0).\n\n"
        "A recording (MCAP, e.g. 'cellbridge record rec.mcap --serial'; its 'serial' topic is\n"
        "the daemon's reads of its lines) prints one JSON line per event in the order the\n"
        "daemon read and published them: {\"t\", \"in\": link, \"frame\"} for each frame of\n"
        "a read, {\"t\", \"out\": topic, \"message\"} for each message of --topics it\n"
        "published after. With --run the recorded messages are left aside and the daemon\n"
        "is run offline on the reads (docs/daemon.md, the offline driver): each read's\n"
        "frames are followed by the messages they caused now.\n\n"
        "examples:\n"
        "  cellbridge decode capture.bin\n"
        "  echo '00 02 04 02 01 ... 00' | cellbridge decode --hex -\n"
        "  cellbridge decode rec.mcap --topics contact,element\n"
        "  cellbridge decode tests/data/golden/fragments.mcap --run --topics contact"
    )
    parser.add_argument("input", help="capture file, a recording (.mcap), or - for standard input")
    parser.add_argument("--hex", action="store_true",
                        help="input is hexadecimal text (whitespace ignored) instead of raw bytes")
    parser.add_argument("--topics", default="contact",
                        help="a recording: the daemon's topics printed beside the frames, comma-separated "
                             "(default contact; 'all' for every one; 'none' for frames only)")
    parser.add_argument("--run", action="store_true",
                        help="a recording: run the daemon offline on its reads instead of printing what it "
                             "recorded (default config, one link per recorded link; --config for another)")
    parser.add_argument("--config", default=None, metavar="TOML",
                        help="with --run: the daemon's config file (its [[link]] names must be the recording's)")


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, Frame):
        return frame_to_json(obj)
    if isinstance(obj, bytes):
        return obj.hex()
    if is_dataclass(obj):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return int(obj) if isinstance(obj, int) else obj  # enum members as their numbers


def frame_to_json(frame: Frame) -> dict[str, Any]:
    """A frame as plain JSON-able data (bytes as hex), led by the frame type's name.

    The form used by ``cellbridge decode`` and by the test vectors of docs/protocol.md.
    """
    d: dict[str, Any] = {"type": frame.type.name}
    d.update({f.name: _jsonable(getattr(frame, f.name)) for f in fields(frame)})
    return d


def run(args: argparse.Namespace) -> int:
    from cellbridge.recording.mcapfile import MAGIC

    if args.input != "-" and not args.hex:
        try:
            with open(args.input, "rb") as fh:
                head = fh.read(len(MAGIC))
        except OSError as exc:
            print(f"cellbridge decode: cannot read {args.input}: {exc.strerror}", file=sys.stderr)
            return 2
        if head == MAGIC:
            return _recording(args)
    if args.run or args.config:
        print("cellbridge decode: --run and --config take a recording (.mcap)", file=sys.stderr)
        return 2
    try:
        if args.input == "-":
            raw = sys.stdin.buffer.read()
        else:
            with open(args.input, "rb") as fh:
                raw = fh.read()
    except OSError as exc:
        print(f"cellbridge decode: cannot read {args.input}: {exc.strerror}", file=sys.stderr)
        return 2
    if args.hex:
        try:
            raw = bytes.fromhex("".join(raw.decode("ascii", "replace").split()))
        except ValueError as exc:
            print(f"cellbridge decode: input is not hexadecimal: {exc}", file=sys.stderr)
            return 2
    decoder, reassembler = StreamDecoder(), Reassembler()
    try:
        for frame in decoder.feed_iter(raw):
            whole = reassembler.receive(frame, 0.0)
            if whole is not None:
                print(json.dumps(frame_to_json(whole)))
    except BrokenPipeError:  # read by `head` (README: decode capture.bin | head): it has what it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    print(json.dumps({"stream": decoder.counters(), "reassembly": reassembler.counters()}), file=sys.stderr)
    return 0


class _Lines:
    """Each link's frames, decoded as the daemon reads them (fragments reassembled)."""

    def __init__(self) -> None:
        self.decoders: dict[str, tuple[StreamDecoder, Reassembler]] = {}

    def frames(self, link: str, data: bytes) -> list[dict[str, Any]]:
        decoder, reassembler = self.decoders.setdefault(link, (StreamDecoder(), Reassembler()))
        out = []
        for frame in decoder.feed_iter(data):
            whole = reassembler.receive(frame, 0.0)
            if whole is not None:
                out.append(frame_to_json(whole))
        return out

    def counters(self) -> dict[str, Any]:
        return {link: {"stream": d.counters(), "reassembly": r.counters()} for link, (d, r) in self.decoders.items()}


def _recording(args: argparse.Namespace) -> int:
    """A recording: its reads' frames, each followed by the messages it caused (recorded, or
    made now by the daemon run offline with ``--run``)."""
    from cellbridge.daemon.shell.publisher import TOPICS
    from cellbridge.recording import codec
    from cellbridge.recording.mcapfile import NotARecording, ReadResult, read_payloads

    messages = [t for t in TOPICS if t != "serial"]  # (the reads are the serial topic: always shown)
    words = {t.strip() for t in args.topics.split(",") if t.strip()}
    topics = set() if words == {"none"} else set(messages) if words == {"all"} else words
    unknown = sorted(topics - set(TOPICS))
    if unknown:  # a typo ('contacts') printed frames and never a message, without a word
        print(f"cellbridge decode: --topics: the daemon has no topic {unknown[0]!r} (topics: {', '.join(messages)}; "
              "or all, or none)", file=sys.stderr)
        return 2
    result = ReadResult()
    lines = _Lines()
    out = sys.stdout

    def show_read(t: Any, link: str, data: bytes) -> None:
        when = t if isinstance(t, (int, float)) and math.isfinite(t) else None
        for frame in lines.frames(link, data):
            out.write(json.dumps({"t": when, "in": link, "frame": frame}) + "\n")

    def show_message(t: Any, topic: str, payload: dict[str, Any]) -> None:
        when = t if isinstance(t, (int, float)) and math.isfinite(t) else None
        body = codec.encode(topic, payload).decode()  # strict JSON, as recordings keep it
        out.write(f'{{"t": {json.dumps(when)}, "out": {json.dumps(topic)}, "message": {body}}}\n')

    try:
        if not args.run:
            for m, payload in read_payloads(args.input, result, topics | {"serial"}):
                if m.topic == "serial":
                    show_read(payload.get("t_read", payload.get("t_host")), str(payload.get("link")),
                              bytes(payload.get("data") or b""))
                else:
                    show_message(payload.get("t_host"), m.topic, payload)
        else:
            reads = [(float(p["t_host"]), str(p.get("link")), bytes(p.get("data") or b""))
                     for _, p in read_payloads(args.input, result, {"serial"})
                     if isinstance(p.get("t_host"), (int, float)) and math.isfinite(p["t_host"])]
            _run_offline(args, reads, topics, show_read, show_message)
    except BrokenPipeError:  # the reader went away (| head): nothing more to say (an OSError: caught first)
        sys.stderr.close()
        return 0
    except NotARecording as exc:  # names the file itself
        print(f"cellbridge decode: {exc}", file=sys.stderr)
        return 1
    except (OSError, ValueError) as exc:
        print(f"cellbridge decode: {args.input}: {exc}", file=sys.stderr)
        return 1
    problem = result.problem(args.input)
    if problem:
        print(f"cellbridge decode: {problem}", file=sys.stderr)
    print(json.dumps({"links": lines.counters()}), file=sys.stderr)
    return 0


def _run_offline(args: argparse.Namespace, reads: list[tuple[float, str, bytes]], topics: set[str],
                 show_read: Any, show_message: Any) -> None:
    """The daemon offline on ``reads`` (time, link, bytes): every read shown before the
    messages of the same or a later time, as the daemon feeds a read before it looks."""
    from cellbridge.daemon.core.config import ConfigError, load_config, parse_config
    from cellbridge.daemon.shell.offline import OfflineDaemon

    links = sorted({link for _, link, _ in reads})
    try:
        config = (load_config(args.config) if args.config
                  else parse_config({"link": [{"name": n, "url": f"/dev/null-{n}"} for n in links]}, "decode --run"))
    except ConfigError as exc:
        raise ValueError("config: " + "; ".join(line.strip() for line in str(exc).splitlines())) from None
    reads.sort(key=lambda r: r[0])
    shown = 0
    for o in OfflineDaemon(config, topics=topics or {"contact"}).run(reads):
        while shown < len(reads) and reads[shown][0] <= o.t:
            show_read(*reads[shown])
            shown += 1
        if o.topic in topics:
            show_message(o.t, o.topic, o.payload)
    for r in reads[shown:]:
        show_read(*r)

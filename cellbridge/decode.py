"""``cellbridge decode``: read a captured serial stream and print its frames.

For looking at what a gateway sends: a capture taken with e.g.
``cat /dev/ttyUSB0 > capture.bin`` or a hex dump pasted from a logic analyser.
"""

from __future__ import annotations

import argparse
import json
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
        "examples:\n"
        "  cellbridge decode capture.bin\n"
        "  echo '00 02 04 02 01 ... 00' | cellbridge decode --hex -"
    )
    parser.add_argument("input", help="capture file, or - for standard input")
    parser.add_argument("--hex", action="store_true",
                        help="input is hexadecimal text (whitespace ignored) instead of raw bytes")


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
    for frame in decoder.feed_iter(raw):
        whole = reassembler.receive(frame, 0.0)
        if whole is not None:
            print(json.dumps(frame_to_json(whole)))
    print(json.dumps({"stream": decoder.counters(), "reassembly": reassembler.counters()}), file=sys.stderr)
    return 0

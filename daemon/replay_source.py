"""What a ``replay:FILE`` link reads: a capture file (``.cbcap``) or an MCAP recording.

An MCAP recording made with ``cellbridge record --serial`` keeps every gateway read on
its ``serial`` channel (``link``, ``t_host`` and the bytes, base64 in JSON); a daemon with
``url = "replay:FILE.mcap"`` re-runs its whole pipeline on them, read by read and at the
recorded arrival times, as from a capture file. The link takes the reads of the recorded
link with its own name, or, when the file holds one link only, that one. Capture files
(``CBCAP1``) are read as before (:mod:`cellbridge.daemon.capture`). A recording cut short
(recorder killed) is read to its last whole chunk.
"""

from __future__ import annotations

import base64
import json
from collections.abc import Iterator
from pathlib import Path

from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from cellbridge.daemon.capture import MAGIC as CAPTURE_MAGIC
from cellbridge.daemon.capture import read_capture

MCAP_MAGIC = b"\x89MCAP0\r\n"
SERIAL_TOPIC = "serial"


def read_records(path: str | Path, link: str) -> Iterator[tuple[float, bytes]]:
    """(host time, bytes) of every read of ``link``; ValueError for a file that is neither format."""
    with open(path, "rb") as fh:
        magic = fh.read(8)
    if magic == CAPTURE_MAGIC:
        return read_capture(path)
    if magic == MCAP_MAGIC:
        return _mcap_serial(Path(path), link)
    raise ValueError(f"{path}: neither a cellbridge capture nor an MCAP recording (bad magic)")


def serial_links(path: str | Path) -> dict[str, int]:
    """Reads per recorded link name on the file's serial channel."""
    out: dict[str, int] = {}
    for name, _, _ in _serial_messages(Path(path)):
        out[name] = out.get(name, 0) + 1
    return out


def _serial_messages(path: Path) -> Iterator[tuple[str, float, bytes]]:
    channels: set[int] = set()
    with open(path, "rb") as fh:
        records = StreamReader(fh).records
        while True:
            try:
                rec = next(records)
            except StopIteration:
                return
            except Exception:  # noqa: BLE001 - a recording cut short ends in any of the reader's errors
                return
            if isinstance(rec, Channel) and rec.topic == SERIAL_TOPIC:
                channels.add(rec.id)
            elif isinstance(rec, Message) and rec.channel_id in channels:
                m = json.loads(rec.data)
                # t_read: never stepped with the wall clock (recordings before it: t_host)
                yield str(m.get("link", "")), float(m.get("t_read", m["t_host"])), base64.b64decode(m["data"])


def _mcap_serial(path: Path, link: str) -> Iterator[tuple[float, bytes]]:
    names = serial_links(path)
    if not names:
        raise ValueError(f"{path}: the recording has no serial channel (record with --serial)")
    if link not in names:
        if len(names) > 1:
            raise ValueError(f"{path}: no serial reads of link {link!r} (recorded links: {', '.join(sorted(names))})")
        (link,) = names
    return ((t, data) for name, t, data in _serial_messages(path) if name == link)

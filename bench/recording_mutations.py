"""Damaged and hostile recordings, and a runner that puts ``cellbridge info`` and ``replay`` on them.

Used by tests/test_recording_robust.py (a sample) and bench/bench_recording_fuzz.py (1 000).

**Seeds** (:func:`seeds`): recordings as ``cellbridge record`` makes them, every topic,
small chunks (many of them), zstd, lz4 and uncompressed, one finished and one cut short.

**Mutations** (:func:`mutate`, deterministic in its index):

- ``truncate``: the file cut anywhere;
- ``bitflip``: 1 to 16 bits flipped anywhere; ``overwrite``: a run of random bytes;
- ``length``: an outer record's length, or a chunk's declared uncompressed size,
  compression name length or data length, set to a huge or a wrong value;
- ``frame``: a chunk's zstd frame header overwritten in place (a complete recording);
- ``bomb``: a chunk whose zstd or lz4 data expands far past what it declares, or that
  declares a 256 MB message, or a frame header claiming 4 GB, or a message within the
  size bounds made of a million tiny JSON values, or a chunk of many tiny messages;
- ``json``: a well-formed file whose messages are odd JSON: an array where a map goes,
  numbers for strings, strings for lists, nesting 100 000 deep, integers of 5 000
  digits, invalid UTF-8, base64 that is not;
- ``splice``: chunks duplicated, dropped or swapped, the summary or footer damaged.

**Runner** (:func:`run_all`): each run of ``cellbridge info FILE`` or ``cellbridge replay
--fast FILE`` in a child forked from a process that has imported the command (as the
``cellbridge`` entry point would run it: ``cellbridge.cli.main``, a traceback printed
by the interpreter on an escaping exception), with its own stdout and stderr files; its
exit status, wall time and peak RSS (``wait4``) are taken by the parent.
``python bench/recording_mutations.py DIR`` runs every ``*.mcap`` in DIR and prints one
JSON line per run (how the tests call it: one subprocess).
"""

from __future__ import annotations

import json
import math
import os
import random
import signal
import struct
import subprocess
import sys
import time
import traceback
import zlib
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import lz4.frame
import zstandard

MAGIC = b"\x89MCAP0\r\n"
KINDS = ("truncate", "bitflip", "overwrite", "length", "frame", "bomb", "json", "splice")


# -- seeds ---------------------------------------------------------------------------------------

def _payloads(n: int) -> Iterator[tuple[str, dict[str, Any], float]]:
    """Messages of every topic as a daemon publishes them, 10 ms apart."""
    t0 = 1_750_000_000.0
    for i in range(n):
        t = t0 + 0.01 * i
        yield "element", {"v": 1, "seq": i, "t_host": t, "t_bridge": [1e-6, 2e-6], "bridge": [1, 2],
                          "element": [0, 0], "cycle": [10 + i, 11 + i], "t_sample": [t, t],
                          "c1": [1.5e-11, 1.6e-11], "c2": [1.9e-11, math.inf], "dc1": [math.nan, 1e-14],
                          "dc2": [math.nan, 2e-14], "force": [math.nan, 1.0], "area": [math.nan, 1e-4],
                          "valid": [False, True], "status": [1, 0], "touched": [False, True],
                          "source": "skin-a"}, t
        if i % 5 == 0:
            yield "contact", {"v": 1, "seq": i // 5, "t_host": t, "t_bridge": None, "t_sample": t, "source": "skin-a",
                              "contacts": [{"id": i // 50, "x": 0.04, "y": 0.02, "force": 1.5, "elements": [1, 2],
                                            "cycles": [10 + i, 11 + i], "valid": True}]}, t
        if i % 10 == 0:
            yield "serial", {"v": 1, "seq": i // 10, "t_host": t, "t_read": t, "t_bridge": None, "link": "gw",
                             "data": bytes(range(i % 7, 40)), "source": "skin-a"}, t
        if i % 50 == 0:
            yield "health", {"v": 1, "seq": i // 50, "t_host": t, "t_bridge": None, "source": "skin-a",
                             "links": {"gw": {"connected": True, "bytes": 1000 * i}},
                             "bridges": {"1": {"frames": i, "loss": 0.0}, "2": {"frames": i, "loss": math.nan}}}, t
            yield "topology", {"v": 1, "seq": i // 50, "t_host": t, "t_bridge": None, "source": "skin-a",
                               "bridges": {"1": {"parent": 0, "hops": 1}, "2": {"parent": 1, "hops": 2}},
                               "gateways": {"gw": [1]}, "layout": {"side": 0.02, "ids": [1, 2],
                                                                  "x": [0.0, 0.02], "y": [0.0, 0.0]}}, t


def write_seed(path: Path, compression: str = "zstd", messages: int = 300, chunk_size: int = 3000,
               finish: bool = True) -> Path:
    """A recording made by the recorder's own writer (``finish`` False: as a killed recorder leaves it)."""
    from cellbridge.recording import codec
    from cellbridge.recording.mcapfile import RecordingWriter

    w = RecordingWriter(path, chunk_size=chunk_size, compression=compression, fsync=False,
                        metadata={"endpoint": "tcp://127.0.0.1:5560", "topics": "all"})
    for topic, p, t in _payloads(messages):
        w.add(topic, codec.encode(topic, p), int(t * 1e9), int((t + 0.001) * 1e9), p["seq"])
    if finish:
        w.finish()
    else:
        w.flush()
        w.abandon()
    return path


def seeds(directory: Path) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    return [write_seed(directory / "seed-zstd.mcap"),
            write_seed(directory / "seed-lz4.mcap", compression="lz4"),
            write_seed(directory / "seed-none.mcap", compression="none"),
            write_seed(directory / "seed-cut.mcap", finish=False)]


# -- the file's framing --------------------------------------------------------------------------

def records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of each outer record of a well-formed file."""
    out = []
    pos = len(MAGIC)
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        if pos + 9 + length > len(data):
            break
        out.append((pos, opcode, length))
        if opcode == 0x02:
            break
        pos += 9 + length
    return out


def chunk_record(inner: bytes, compression: str = "zstd", data: bytes | None = None,
                 size: int | None = None, crc: int | None = None) -> bytes:
    """A chunk record holding ``inner`` (records), compressed as said unless ``data`` is given."""
    if data is None:
        data = {"zstd": zstandard.compress, "lz4": lz4.frame.compress, "": bytes}[compression](inner)
    name = compression.encode()
    body = struct.pack("<QQQI", 0, 0, len(inner) if size is None else size,
                       zlib.crc32(inner) if crc is None else crc)
    body += struct.pack("<I", len(name)) + name + struct.pack("<Q", len(data)) + data
    return struct.pack("<BQ", 0x06, len(body)) + body


def channel_record(cid: int, topic: str) -> bytes:
    from mcap.data_stream import RecordBuilder
    from mcap.records import Channel

    b = RecordBuilder()
    Channel(id=cid, topic=topic, message_encoding="json", metadata={}, schema_id=0).write(b)
    return b.end()


def message_record(cid: int, data: bytes, seq: int = 0, t_ns: int = 1_750_000_000 * 10**9) -> bytes:
    return struct.pack("<BQHIQQ", 0x05, 22 + len(data), cid, seq, t_ns, t_ns) + data


def header_record() -> bytes:
    body = struct.pack("<I", 0) + struct.pack("<I", 4) + b"test"
    return struct.pack("<BQ", 0x01, len(body)) + body


def footer(summary_start: int = 0) -> bytes:
    return struct.pack("<BQQQI", 0x02, 20, summary_start, 0, 0) + MAGIC


def file_of(*chunks: bytes, finished: bool = True) -> bytes:
    """Header, the given records, and (``finished``) a data end and a footer without summary."""
    body = MAGIC + header_record() + b"".join(chunks)
    if finished:
        body += struct.pack("<BQI", 0x0F, 4, 0) + footer()
    return body


# -- bombs ---------------------------------------------------------------------------------------

_BOMBS: dict[str, bytes] = {}


def _zstd_stream(total: int, piece: bytes, content_size: bool, prefix: bytes = b"") -> bytes:
    """One zstd frame of ``prefix`` and ``total`` bytes of repeated ``piece``, made in pieces
    (never all in memory)."""
    key = f"z{total}{piece!r}{content_size}{prefix!r}"
    if key not in _BOMBS:
        cctx = zstandard.ZstdCompressor(level=1, write_content_size=content_size)
        obj = cctx.compressobj(size=len(prefix) + total if content_size else -1)
        block = piece * max(1, (1 << 20) // len(piece))
        out = [obj.compress(prefix)]
        left = total
        while left > 0:
            part = block[:left]
            out.append(obj.compress(part))
            left -= len(part)
        out.append(obj.flush())
        _BOMBS[key] = b"".join(out)
    return _BOMBS[key]


BOMB_KINDS = 10


def bomb(kind: int, topic: str = "element") -> bytes:
    """A whole file built around hostile chunks; ``kind`` picks which (0 to BOMB_KINDS - 1);
    its one channel is ``topic``."""
    ch = channel_record(1, topic)
    kind %= BOMB_KINDS
    rng = random.Random(kind)
    if kind == 0:  # one zstd chunk declaring a 256 MB message, sizes honest (an 8 kB file)
        n = 256 << 20
        inner_head = ch + struct.pack("<BQHIQQ", 0x05, 22 + n, 1, 0, 1, 1)
        data = _zstd_stream(n, b" ", True, prefix=inner_head)
        return file_of(chunk_record(b"", data=data, size=len(inner_head) + n, crc=0))
    if kind == 1:  # declares a small chunk, the frame (no content size) expands to 1 GB
        inner = ch + message_record(1, b"{}")
        return file_of(chunk_record(inner, data=_zstd_stream(1 << 30, b"\x00", False), size=len(inner)))
    if kind == 2:  # frame header claims 4 GB of content, the chunk declares the truth
        inner = ch + message_record(1, b"{}")
        frame = zstandard.ZstdCompressor(write_content_size=True).compress(inner)
        fake = zstandard.ZstdCompressor(write_content_size=True).compress(b"\x00" * (1 << 20))
        return file_of(chunk_record(inner, data=fake[:12] + frame[12:], size=len(inner)))
    if kind == 3:  # lz4: a 1 GB expansion declared as a few bytes
        inner = ch + message_record(1, b"{}")
        if "lz4" not in _BOMBS:
            c = lz4.frame.LZ4FrameCompressor()
            parts = [c.begin()] + [c.compress(b"\x00" * (1 << 20)) for _ in range(1024)] + [c.flush()]
            _BOMBS["lz4"] = b"".join(parts)
        return file_of(chunk_record(inner, compression="lz4", data=_BOMBS["lz4"], size=len(inner)))
    if kind == 4:  # within the bounds in bytes, 2.7 million tiny JSON values (a Python object each)
        return file_of(chunk_record(ch + message_record(1, b"[" + b"{}," * 2_700_000 + b"{}]")))
    if kind == 5:  # a chunk of 200 000 tiny messages in a few kB
        return file_of(chunk_record(ch + message_record(1, b'{"v":1,"seq":0,"t_host":1.0}') * 200_000))
    if kind == 6:  # a chunk declaring 2**64 - 1 bytes uncompressed
        return file_of(chunk_record(ch + message_record(1, b"{}"), size=2**64 - 1))
    if kind == 7:  # two chunks at the bounds, of incompressible messages near the largest a message may be
        import base64

        def big() -> bytes:
            pad = base64.b64encode(rng.randbytes(5_900_000))
            return b'{"v":1,"seq":0,"t_host":1.0,"pad":"' + pad + b'"}'
        return file_of(chunk_record(ch + message_record(1, big()) + message_record(1, big()), compression=""),
                       chunk_record(ch + message_record(1, big()) + message_record(1, big())))
    if kind == 8:  # a message just within the value bound, of the costliest values (short strings: ~60 B each)
        letters = b"abcdefghijklmnopqrstuvwxyz"
        values = b",".join(b'"%c%c"' % (rng.choice(letters), rng.choice(letters)) for _ in range(990_000))
        return file_of(chunk_record(ch + message_record(1, b'{"v":1,"seq":0,"t_host":1.0,"x":[' + values + b"]}")))
    # kind 9: many small messages that do not compress much (a dense recording)
    msgs = [message_record(1, b'{"v":1,"seq":%d,"t_host":%f,"x":%d}' % (i, rng.random() * 1e9, rng.getrandbits(60)))
            for i in range(50_000)]
    return file_of(chunk_record(ch + b"".join(msgs[:25_000])), chunk_record(b"".join(msgs[25_000:])))


# -- odd JSON --------------------------------------------------------------------------------------

ODD_JSON = [
    b"[1, 2, 3]", b'"a string"', b"42", b"null", b'{"bridge": "abc", "t_host": 1.0}',
    b'{"bridge": [1e400, -1, "7", null, {"a": 1}], "t_host": "later"}', b'{"contacts": [1, "x", null, [2]]}',
    b'{"contacts": {"id": 3}}', b'{"bridges": 5}', b'{"bridges": [1, 2]}', b'{"source": 5, "seq": "no"}',
    b'{"link": ["gw"], "data": "!!!not base64!!!"}', b'{"link": "gw", "data": 12}', b"[" * 100_000 + b"]" * 100_000,
    b'{"a":' * 50_000 + b"1" + b"}" * 50_000, b'{"seq": ' + b"9" * 5000 + b"}", b'{"t_host": 1e400}',
    b"\xff\xfe not utf-8", b'{"contacts": [{"id": "x", "force": "NaN"}, {"force": 1e400}]}', b"",
    b'{"bridges": {"99999999999": {}, "-1": {}, "x": {}}}', b'{"v": 1, "x": "' + b"\\ud800" * 10 + b'"}',
]
TOPICS = ("element", "raw", "contact", "health", "topology", "serial", "other")


def odd_json_file(rng: random.Random) -> bytes:
    """A well-formed finished file: a few good messages, then odd JSON on every topic."""
    from cellbridge.recording import codec

    chans = b"".join(channel_record(i + 1, t) for i, t in enumerate(TOPICS))
    good = [message_record(1 + TOPICS.index(t), codec.encode(t, p), p["seq"])
            for t, p, _ in _payloads(20) if t in TOPICS]
    odd = [message_record(rng.randrange(len(TOPICS)) + 1, rng.choice(ODD_JSON), i) for i in range(rng.randint(1, 6))]
    mixed = good[:10] + odd + good[10:]
    return file_of(chunk_record(chans + b"".join(mixed[:len(mixed) // 2])),
                   chunk_record(b"".join(mixed[len(mixed) // 2:]), compression=rng.choice(["zstd", "lz4", ""])))


# -- mutations -----------------------------------------------------------------------------------

def mutate(seed: bytes, index: int) -> tuple[str, bytes]:
    """The ``index``-th mutation of a seed: (its kind, the bytes)."""
    rng = random.Random(index * 7919 + len(seed))
    kind = KINDS[index % len(KINDS)]
    data = bytearray(seed)
    recs = records(seed)
    chunks = [r for r in recs if r[1] == 0x06]
    if kind == "truncate":
        return kind, bytes(data[:rng.randrange(len(data))])
    if kind == "bitflip":
        for _ in range(rng.randint(1, 16)):
            i = rng.randrange(len(data))
            data[i] ^= 1 << rng.randrange(8)
        return kind, bytes(data)
    if kind == "overwrite":
        i = rng.randrange(len(data))
        n = rng.randint(1, 64)
        data[i:i + n] = rng.randbytes(min(n, len(data) - i))
        return kind, bytes(data)
    if kind == "length":
        huge = rng.choice([2**64 - 1, 2**63, 2**32 + 5, len(data) * 2, 256 << 20, rng.randrange(1, 200), 0])
        pos, opcode, _ = rng.choice(chunks if chunks and rng.random() < 0.7 else recs)
        if opcode == 0x06 and rng.random() < 0.75:
            body = pos + 9
            (name_len,) = struct.unpack_from("<I", data, body + 28)
            field = rng.choice(["size", "name", "data"])
            if field == "size":
                struct.pack_into("<Q", data, body + 16, huge)
            elif field == "name":
                struct.pack_into("<I", data, body + 28, huge & 0xFFFFFFFF)
            else:
                struct.pack_into("<Q", data, body + 32 + name_len, huge)
        else:
            struct.pack_into("<Q", data, pos + 1, huge)
        return kind, bytes(data)
    if kind == "frame":
        if not chunks:
            return kind, bytes(data)
        pos, _, _ = rng.choice(chunks)
        (name_len,) = struct.unpack_from("<I", data, pos + 9 + 28)
        at = pos + 9 + 32 + name_len + 8
        data[at:at + 6] = rng.randbytes(6)
        return kind, bytes(data)
    if kind == "bomb":
        return kind, bomb(index // len(KINDS))
    if kind == "json":
        return kind, odd_json_file(rng)
    # splice
    how = rng.randrange(5)
    if how == 0 and len(chunks) > 2:  # a chunk twice
        pos, _, length = rng.choice(chunks)
        piece = data[pos:pos + 9 + length]
        data[pos:pos] = piece
    elif how == 1 and len(chunks) > 2:  # a chunk dropped
        pos, _, length = rng.choice(chunks)
        del data[pos:pos + 9 + length]
    elif how == 2 and len(chunks) > 2:  # two chunks swapped
        (a, _, la), (b, _, lb) = sorted(rng.sample(chunks, 2))
        ca, cb = bytes(data[a:a + 9 + la]), bytes(data[b:b + 9 + lb])
        data[b:b + 9 + lb] = ca
        data[a:a + 9 + la] = cb
    elif how == 3:  # the summary overwritten
        foot = recs[-1][0] if recs and recs[-1][1] == 0x02 else len(data) - 40
        start = max(8, foot - rng.randint(1, 400))
        data[start:foot] = rng.randbytes(foot - start)
    else:  # the footer's summary start pointing anywhere
        if recs and recs[-1][1] == 0x02:
            struct.pack_into("<Q", data, recs[-1][0] + 9, rng.choice([0, 1, 2**64 - 1, len(data) - 20, 9]))
    return kind, bytes(data)


def corpus(directory: Path, count: int) -> list[tuple[Path, str]]:
    """``count`` mutated recordings written into ``directory``: (path, kind)."""
    directory.mkdir(parents=True, exist_ok=True)
    base = [p.read_bytes() for p in seeds(directory / "seeds")]
    out = []
    for i in range(count):
        kind, data = mutate(base[(i // len(KINDS)) % len(base)], i)
        path = directory / f"m{i:04d}-{kind}.mcap"
        path.write_bytes(data)
        out.append((path, kind))
    return out


# -- the runner ----------------------------------------------------------------------------------

@dataclass
class Run:
    file: str
    tool: str
    code: int  # exit status; -N: killed by signal N (a timeout: SIGKILL)
    seconds: float
    rss_mb: float  # peak resident set size of the run (its process, imports included)
    stderr: str
    stdout_bytes: int


def command(tool: str, path: Path) -> list[str]:
    if tool == "info":
        return ["info", str(path)]
    return ["replay", "--fast", "--endpoint", "tcp://127.0.0.1:*", str(path)]


def _child(argv: list[str], out: str, err: str) -> None:
    """In the forked child: the command as the ``cellbridge`` entry point runs it."""
    code = 1
    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_DFL)
        os.dup2(os.open(out, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), 1)
        os.dup2(os.open(err, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), 2)
        from cellbridge.cli import main

        try:
            code = main(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        except BaseException:
            traceback.print_exc()
            code = 1
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(code)


_EXEC_RUNNER = """
import os, signal, sys, time
exe, out, err, timeout = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
pid = os.fork()
if pid == 0:
    try:
        os.dup2(os.open(out, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), 1)
        os.dup2(os.open(err, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), 2)
        os.execv(exe, [exe, *sys.argv[5:]])
    finally:
        os._exit(127)
deadline = time.monotonic() + timeout
while True:
    wpid, status, usage = os.wait4(pid, os.WNOHANG)
    if wpid:
        break
    if time.monotonic() > deadline:
        os.kill(pid, signal.SIGKILL)
        wpid, status, usage = os.wait4(pid, 0)
        break
    time.sleep(0.002)
print(os.waitstatus_to_exitcode(status), usage.ru_maxrss)
"""


def run_one(argv: list[str], workdir: Path, timeout: float = 60.0, exec_cli: bool = False) -> tuple[int, float, float, str, int]:
    """(exit status, seconds, peak RSS MB, stderr, stdout bytes) of one command, forked (or exec'd)."""
    out, err = workdir / "stdout", workdir / "stderr"
    sys.stdout.flush()
    sys.stderr.flush()
    t0 = time.monotonic()
    if exec_cli:
        # Exec'd from a small runner, not forked from this process: a child's peak RSS
        # counts what it had before its exec, and a forked copy of a test worker that has
        # imported the whole project (and run other tests) starts at that worker's size.
        exe = str(Path(sys.executable).with_name("cellbridge"))
        runner = subprocess.run([sys.executable, "-S", "-c", _EXEC_RUNNER, exe, str(out), str(err), str(timeout),
                                 *argv], capture_output=True, text=True, timeout=timeout + 30)
        code, rss = (int(x) for x in runner.stdout.split())
        return (code, time.monotonic() - t0, rss / 1024, err.read_text(errors="replace"), out.stat().st_size)
    else:
        pid = os.fork()
        if pid == 0:
            _child(argv, str(out), str(err))
    deadline = t0 + timeout
    while True:
        wpid, status, usage = os.wait4(pid, os.WNOHANG)
        if wpid:
            break
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            wpid, status, usage = os.wait4(pid, 0)
            break
        time.sleep(0.002)
    seconds = time.monotonic() - t0
    return (os.waitstatus_to_exitcode(status), seconds, usage.ru_maxrss / 1024,
            err.read_text(errors="replace"), out.stat().st_size)


def run_all(files: list[Path], workdir: Path, tools: tuple[str, ...] = ("info", "replay"),
            exec_cli: bool = False, timeout: float = 60.0) -> Iterator[Run]:
    import cellbridge.cli

    cellbridge.cli.build_parser()  # every command's module imported once, before the forks
    workdir.mkdir(parents=True, exist_ok=True)
    for path in files:
        for tool in tools:
            code, seconds, rss, stderr, nout = run_one(command(tool, path), workdir, timeout, exec_cli)
            yield Run(str(path), tool, code, seconds, rss, stderr, nout)


def verdict(run: Run) -> str:
    """Empty if the run ended as it must: exit 0 or 1, no traceback, and on stderr nothing but
    its own lines (info: one line naming the file when it exits 1; replay: its final JSON line,
    after at most one line naming the file)."""
    lines = run.stderr.splitlines()
    if "Traceback" in run.stderr:
        return "traceback"
    if run.code not in (0, 1):
        return f"exit status {run.code}"
    own = f"cellbridge {run.tool}: {run.file}: "
    if run.tool == "info":
        if run.code == 0 and lines:
            return f"exit 0 with stderr {lines[:2]}"
        if run.code == 1 and (len(lines) != 1 or not lines[0].startswith(own)):
            return f"exit 1 without one line naming the file: {lines[:3]}"
        return ""
    if not lines or not lines[-1].startswith("{"):
        return f"no final JSON line: {lines[-3:]}"
    try:
        json.loads(lines[-1])
    except ValueError:
        return "final line is not JSON"
    rest = lines[:-1]
    if run.code == 0 and rest:
        return f"exit 0 with other lines: {rest[:2]}"
    if run.code == 1 and (len(rest) != 1 or not rest[0].startswith(own)):
        return f"exit 1 without one line naming the file: {rest[:3]}"
    return ""


if __name__ == "__main__":
    directory = Path(sys.argv[1])
    for r in run_all(sorted(directory.glob("*.mcap")), directory / "run"):
        print(json.dumps(asdict(r)), flush=True)

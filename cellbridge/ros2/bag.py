"""ROS 2 bags: a rosbag2 directory of MCAP files (ROS 2 profile, CDR) and its ``metadata.yaml``.

What ``ros2 bag record -s mcap`` leaves, and what ``ros2 bag play``, ``ros2 bag info``,
rosbags and Foxglove read as typed messages::

    skin/                  the bag (a directory)
      metadata.yaml        rosbag2's description: topics, types, QoS, counts, files, times
      skin_0.mcap          profile "ros2": per type a "ros2msg" schema (the .msg text and those
      skin_1.mcap ...      it uses), per topic a "cdr" channel with its offered QoS; the messages

The MCAP files are written as the JSON recordings are (:mod:`cellbridge.recording.mcapfile`):
chunked, each chunk in the kernel as soon as it is finished, so a recorder killed
outright leaves files that read up to their last whole chunk. ``metadata.yaml`` is
rewritten (atomically) at every :meth:`BagWriter.flush` as well as at the end, so such a
bag still opens, with the counts of its last flush.

``metadata.yaml`` is rosbag2's version 5 (Humble's; every later rosbag2 reads it).

A write that fails (a full disk, a file-size limit) leaves the file as it was after its
last whole chunk: what was written of the chunk in progress is cut off again, and the
counts (:attr:`BagWriter.counts`, the files' and ``metadata.yaml``'s) go back to what the
files hold. Without that the recorder said it recorded the messages of a chunk that never
reached the disk whole, which no reader finds.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from cellbridge._version import __version__
from cellbridge.recording.mcapfile import _UnbufferedFile
from cellbridge.ros2 import msgdefs
from cellbridge.ros2.qos import TopicSpec
from cellbridge.ros2.types import cdr

PROFILE = "ros2"
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
METADATA_VERSION = 5


class BagExists(FileExistsError):
    """The bag's directory exists and is not empty (rosbag2 refuses to write into one too)."""


@dataclass
class _File:
    path: Path
    first_ns: int = 0
    last_ns: int = 0
    messages: int = 0


class BagWriter:
    """One bag: ``add`` messages of the topics in ``specs``; ``flush`` often, ``finish`` at the end.

    A new MCAP file is started when the current one reaches ``rotate_bytes`` or is
    ``rotate_seconds`` old (by the log time), as ``ros2 bag record --max-bag-size`` splits.
    Every method may raise OSError (a full disk): the files keep their whole chunks."""

    def __init__(self, path: str | Path, specs: dict[str, TopicSpec], *, chunk_size: int = 1 << 20,
                 compression: str = "zstd", fsync: bool = True, rotate_bytes: int = 0,
                 rotate_seconds: float = 0.0, metadata: dict[str, str] | None = None) -> None:
        self.path = Path(path)
        if self.path.exists() and (not self.path.is_dir() or any(self.path.iterdir())):
            raise BagExists(f"{self.path} exists (a bag is a new directory)")
        self.path.mkdir(parents=True, exist_ok=True)
        self.specs = specs
        self._chunk_size = chunk_size
        self._compression = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                             "none": CompressionType.NONE}[compression]
        self._fsync = fsync
        self.rotate_bytes = rotate_bytes
        self.rotate_ns = int(rotate_seconds * 1e9)
        self._metadata = metadata or {}
        self.files: list[_File] = []
        self.counts: dict[str, int] = {k: 0 for k in specs}
        self._writer: Writer | None = None
        self._out: _UnbufferedFile | None = None
        self._channels: dict[str, int] = {}
        self.finished = False
        # what the files hold whole: the current file's length and the counts then
        self._whole: tuple[int, dict[str, int], _File] = (0, dict(self.counts), _File(self.path))
        self._open_next()
        self.write_metadata()

    @property
    def messages(self) -> int:
        return sum(self.counts.values())

    def _open_next(self) -> None:
        path = self.path / f"{self.path.name}_{len(self.files)}.mcap"
        self._out = _UnbufferedFile(path, self._fsync)
        try:
            self._writer = Writer(self._out, chunk_size=self._chunk_size, compression=self._compression)  # type: ignore[arg-type]  # a file-like of our own (write, tell, flush), not an IO[bytes]
            self._writer.start(profile=PROFILE, library=f"cellbridge {__version__}")
            if self._metadata:
                self._writer.add_metadata("cellbridge", self._metadata)
        except BaseException:
            self._out.close()
            raise
        self._channels = {}
        self.files.append(_File(path))
        self._mark_whole()

    def _mark_whole(self) -> None:
        """Everything added so far is in the current file, whole (a chunk was just written)."""
        assert self._out is not None
        f = self.files[-1]
        self._whole = (self._out.tell(), dict(self.counts), _File(f.path, f.first_ns, f.last_ns, f.messages))

    def _cut_back(self) -> None:
        """After a failed write: the current file ends at its last whole chunk again, and the
        counts are those of what the files hold."""
        pos, counts, f = self._whole
        self.counts = counts
        if self.files and self.files[-1].path == f.path:
            self.files[-1] = f
        if self._out is not None and self._out.fd >= 0:
            try:
                os.ftruncate(self._out.fd, pos)  # frees space: possible on a full disk
            except OSError:
                pass

    def _channel(self, key: str) -> int:
        ch = self._channels.get(key)
        if ch is None:
            assert self._writer is not None
            spec = self.specs[key]
            sid = self._writer.register_schema(spec.ros_type, SCHEMA_ENCODING, msgdefs.schema(spec.ros_type).encode())
            ch = self._writer.register_channel(spec.name, MESSAGE_ENCODING, sid,
                                               metadata={"offered_qos_profiles": spec.offered_qos_yaml()})
            self._channels[key] = ch
        return ch

    def add(self, key: str, message: Any, log_ns: int, publish_ns: int | None = None) -> None:
        """One message (a :mod:`cellbridge.ros2.types` object) of topic ``key`` at ``log_ns``."""
        data = cdr(message)
        try:
            self._add(key, data, log_ns, publish_ns)
        except OSError:
            self._cut_back()
            raise

    def _add(self, key: str, data: bytes, log_ns: int, publish_ns: int | None) -> None:
        current = self.files[-1]
        if current.messages and ((self.rotate_bytes and self._out is not None and self._out.tell() >= self.rotate_bytes)
                                 or (self.rotate_ns and log_ns - current.first_ns >= self.rotate_ns)):
            self._close_current()
            self._open_next()
            current = self.files[-1]
        assert self._writer is not None and self._out is not None
        before = self._out.tell()
        self._writer.add_message(self._channel(key), log_time=log_ns, data=data,
                                 publish_time=log_ns if publish_ns is None else publish_ns)
        if not current.messages:
            current.first_ns = current.last_ns = log_ns
        current.first_ns, current.last_ns = min(current.first_ns, log_ns), max(current.last_ns, log_ns)
        current.messages += 1
        self.counts[key] += 1
        if self._out.tell() != before:  # the chunk with this message in it was written
            self._mark_whole()

    def flush(self) -> None:
        """Finish the chunk in progress and write ``metadata.yaml``: all so far survives a kill."""
        if self._writer is not None:
            try:
                self._writer.flush()
            except OSError:
                self._cut_back()
                raise
            self._mark_whole()
        self.write_metadata()

    def finish(self) -> None:
        """Summary and index of the last file, and the final ``metadata.yaml``."""
        if not self.finished:
            self.finished = True
            try:
                self._close_current()
            except OSError:
                self._cut_back()
                raise
            finally:
                self.write_metadata()

    def _close_current(self) -> None:
        if self._writer is not None and self._out is not None:
            w, out = self._writer, self._out
            try:
                w.finish()
                out.flush()
                f = self.files[-1]  # finished whole: all counted so far is in the files
                self._whole = (out.tell(), dict(self.counts), _File(f.path, f.first_ns, f.last_ns, f.messages))
            except OSError:
                self._cut_back()  # (while the file is still open)
                raise
            finally:
                self._writer = self._out = None
                out.close()

    def abandon(self) -> None:
        """Close without writing more (after a write error); ``metadata.yaml`` says what the
        files hold, if there is room to say it."""
        self.finished = True
        if self._out is not None:
            self._out.close()
        self._writer = self._out = None
        try:
            self.write_metadata()
        except OSError:
            pass

    def write_metadata(self) -> None:
        text = metadata_yaml(self.specs, self.counts, self.files)
        tmp = self.path / ".metadata.yaml.tmp"
        tmp.write_text(text)
        os.replace(tmp, self.path / "metadata.yaml")


def _q(s: str) -> str:
    """A YAML double-quoted scalar (JSON's escapes are YAML's)."""
    return json.dumps(s)


def metadata_yaml(specs: dict[str, TopicSpec], counts: dict[str, int], files: list[_File]) -> str:
    """rosbag2's ``metadata.yaml`` (version 5) of a bag with these topics and files."""
    used = [f for f in files if f.messages]
    start = min((f.first_ns for f in used), default=0)
    end = max((f.last_ns for f in used), default=0)
    lines = ["rosbag2_bagfile_information:", f"  version: {METADATA_VERSION}", "  storage_identifier: mcap",
             "  duration:", f"    nanoseconds: {end - start}", "  starting_time:",
             f"    nanoseconds_since_epoch: {start}", f"  message_count: {sum(counts.values())}",
             "  topics_with_message_count:"]
    for key, spec in specs.items():
        lines += ["    - topic_metadata:", f"        name: {_q(spec.name)}", f"        type: {_q(spec.ros_type)}",
                  "        serialization_format: cdr", f"        offered_qos_profiles: {_q(spec.offered_qos_yaml())}",
                  f"      message_count: {counts.get(key, 0)}"]
    lines += ['  compression_format: ""', '  compression_mode: ""', "  relative_file_paths:"]
    lines += [f"    - {_q(f.path.name)}" for f in files]
    lines.append("  files:")
    for f in files:
        lines += [f"    - path: {_q(f.path.name)}", "      starting_time:",
                  f"        nanoseconds_since_epoch: {f.first_ns}", "      duration:",
                  f"        nanoseconds: {f.last_ns - f.first_ns}", f"      message_count: {f.messages}"]
    return "\n".join(lines) + "\n"

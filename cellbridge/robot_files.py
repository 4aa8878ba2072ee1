"""The files of a ``cellbridge robot run --out DIR``: written whole or said to be partial,
read back checked line by line.

``DIR/truth.jsonl`` holds one true contact a line (:meth:`Truth.to_dict`),
``DIR/contacts.jsonl`` one published frame a line (``{"t": ..., "contacts": [...]}``;
``cellbridge sub contact``'s lines, ``{"topic": "contact", "payload": {...}}`` with the
payload's ``t_sample`` on the truth's clock, are read too), and ``DIR/run.json`` what made
them: the options, whether the run finished (``complete``, and ``until``: the virtual
second its contacts reach), and each file's SHA-256, so that a ``truth.jsonl`` scored
against the ``contacts.jsonl`` of another run is refused rather than scored as a run that
detected nothing.

Why this module: the score table is what a user trusts, so what it is computed from is
read strictly. Every line is a JSON object of the fields the scorer uses, of their types,
finite where a number must be (a contact's ``cov`` may hold ``inf``: an axis the readings
leave open); a line that is not is refused with the file and line named
(:class:`RunFileError`), never skipped, and lines of other topics in a recording are
counted. A line longer than :data:`MAX_LINE` bytes is refused before it is parsed.
Files are written under ``*.partial`` names and renamed when whole: a run stopped
while writing, or a disk that fills, leaves no file that looks whole.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import stat
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from cellbridge.errors import CellbridgeError

if TYPE_CHECKING:
    from cellbridge.tactile.skin_geometry import SkinGeometry

__all__ = ["MAX_LINE", "RunFileError", "RunFiles", "prepare_out", "read_run", "write_run"]

MAX_LINE = 64 << 20  #: bytes of one line: a true contact takes about 200 kB a second of its press (1 ms steps)
TRUTH = "truth.jsonl"
CONTACTS = "contacts.jsonl"
RUN = "run.json"
FORMAT = 1


#: the fields of a published contact the scorer reads (robot_score.score); the rest is not kept
SCORED = ("id", "missed", "link", "position", "force", "valid", "observable", "cov")


class RunFileError(CellbridgeError, ValueError):
    """A run's file that cannot be scored; the message names the file and the line."""


@dataclass
class RunFiles:
    """What :func:`read_run` read: the truths, the frames ``(t, contacts)``, ``run.json``
    (empty without one), and notes for the user (lines skipped, checks not made)."""

    truths: list[dict[str, Any]]
    frames: list[tuple[float, list[dict[str, Any]]]]
    meta: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    truth_lines: list[int] = field(default_factory=list)  #: the line of each truth in its file
    truth_path: str = ""

    def check_on(self, skin: SkinGeometry) -> None:
        """Refuse (:class:`RunFileError`, naming the line) a truth on a link ``skin`` has not
        (files of another skin) or whose atlas place at some step is off its link's patches
        by more than an element's side: it could be matched to nothing, or its reports'
        errors measured against a place on no skin."""
        links = {c.link for c in skin.charts}
        charts = skin.charts
        for d, n in zip(self.truths, self.truth_lines):
            where = f"{self.truth_path}:{n}: not a true contact on this skin"
            if d["link"] not in links:
                raise RunFileError(f"{where}: link {d['link']!r} is not a link of the arm's skin ({', '.join(sorted(links))})")
            if not d["atlas"]:
                continue
            xy = np.asarray(d["atlas"], dtype=np.float64)
            ci = skin.chart_at(xy[:, 0], xy[:, 1])
            x0 = np.array([charts[i].x0 for i in ci]) - skin.side
            y0 = np.array([charts[i].y0 for i in ci]) - skin.side
            x1 = x0 + np.array([charts[i].width for i in ci]) + 2 * skin.side
            y1 = y0 + np.array([charts[i].height for i in ci]) + 2 * skin.side
            ok = (x0 <= xy[:, 0]) & (xy[:, 0] <= x1) & (y0 <= xy[:, 1]) & (xy[:, 1] <= y1)
            ok &= np.array([charts[i].link == d["link"] for i in ci])
            if not ok.all():
                k = int(np.argmin(ok))
                raise RunFileError(f"{where}: its atlas place {tuple(xy[k])} at step {k} is not on link {d['link']}")


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _vector(v: Any, n: int) -> bool:
    return isinstance(v, list) and len(v) == n and all(_finite(x) for x in v)


def _lines(path: str) -> Iterator[tuple[int, Any]]:
    """(line number, parsed JSON) of every non-blank line of ``path``."""
    with open(path, "rb") as fh:
        n = 0
        while True:
            raw = fh.readline(MAX_LINE + 1)
            if not raw:
                return
            n += 1
            if len(raw) > MAX_LINE:
                raise RunFileError(f"{path}:{n}: line longer than {MAX_LINE >> 20} MiB: not a run's file")
            if not raw.strip():
                continue
            try:
                text = raw.decode("utf-8")
            except UnicodeDecodeError:
                raise RunFileError(f"{path}:{n}: not UTF-8 text (a binary file?)") from None
            try:
                yield n, json.loads(text)
            except ValueError as exc:
                cut = "" if raw.endswith(b"\n") else " (the file ends inside it: cut short?)"
                raise RunFileError(f"{path}:{n}: not JSON{cut}: {exc}") from None


def _truth_problem(d: Any) -> str | None:
    """What is wrong with a truth record for the scorer, or None."""
    if not isinstance(d, dict):
        return "not a JSON object"
    for key in ("link", "kind"):
        if not isinstance(d.get(key), str) or not d[key]:
            return f"'{key}' is not a name"
    for key in ("start", "end", "pad"):
        if not _finite(d.get(key)):
            return f"'{key}' is not a finite number"
    if d["end"] < d["start"]:
        return "'end' is before 'start'"
    if d["pad"] <= 0:
        return "'pad' is not positive"
    t = d.get("t")
    if not isinstance(t, list) or not all(_finite(x) for x in t):
        return "'t' is not a list of finite numbers"
    if any(b < a for a, b in zip(t, t[1:])):
        return "'t' goes back in time"
    for key, n in (("point", 3), ("atlas", 2), ("force", 0)):
        v = d.get(key)
        if not isinstance(v, list) or len(v) != len(t):
            return f"'{key}' is not a list as long as 't' ({len(t)})"
        if not all(_finite(x) if n == 0 else _vector(x, n) for x in v):
            return f"'{key}' holds a value that is not {'a finite number' if n == 0 else f'{n} finite numbers'}"
    return None


def _contact_problem(c: Any) -> str | None:
    """What is wrong with a published contact for the scorer, or None."""
    if not isinstance(c, dict):
        return "a contact that is not a JSON object"
    if not isinstance(c.get("id"), int) or isinstance(c["id"], bool):
        return "a contact whose 'id' is not an integer"
    missed = c.get("missed", 0)
    if not isinstance(missed, int) or isinstance(missed, bool) or missed < 0:
        return f"contact {c['id']}: 'missed' is not a count"
    if missed:
        return None  # not scored: its fields are an earlier estimate's
    if c.get("link") is not None and not isinstance(c["link"], str):
        return f"contact {c['id']}: 'link' is not a name"
    if not _vector(c.get("position"), 3):
        return f"contact {c['id']}: 'position' is not 3 finite numbers"
    if c.get("force") is not None and not _number(c["force"]):
        return f"contact {c['id']}: 'force' is not a number"
    if c.get("valid") is not None and not isinstance(c["valid"], bool):
        return f"contact {c['id']}: 'valid' is not true or false"
    obs = c.get("observable")
    if obs is not None and not (isinstance(obs, list) and len(obs) == 2 and all(isinstance(o, bool) for o in obs)):
        return f"contact {c['id']}: 'observable' is not two booleans"
    cov = c.get("cov")
    if cov is not None and not (isinstance(cov, list) and len(cov) == 2 and all(
            isinstance(r, list) and len(r) == 2 and all(v is None or (_number(v) and not math.isnan(v)) for v in r)
            for r in cov) and all(cov[i][i] is None or cov[i][i] >= 0 for i in (0, 1))):
        return f"contact {c['id']}: 'cov' is not a 2x2 covariance"
    return None


def _unnull(c: dict[str, Any]) -> None:
    """``cellbridge sub`` writes numbers that are not finite as null: a variance on ``cov``'s
    diagonal so is infinite (an axis the readings leave open; the daemon's cov holds no
    NaN), and a null force is not known."""
    cov = c.get("cov")
    if isinstance(cov, list):
        c["cov"] = [[math.inf if v is None and i == j else (0.0 if v is None else v) for j, v in enumerate(r)]
                    for i, r in enumerate(cov)]
    if "force" in c and c["force"] is None:
        c["force"] = math.nan


def read_truths(path: str) -> tuple[list[dict[str, Any]], list[int]]:
    """The truths of ``path`` and the line of each."""
    out, lines = [], []
    for n, d in _lines(path):
        problem = _truth_problem(d)
        if problem:
            raise RunFileError(f"{path}:{n}: not a true contact: {problem}")
        out.append(d)
        lines.append(n)
    return out, lines


@dataclass
class _Runs:
    """The daemon runs of a ``cellbridge sub`` recording, told apart by each source's ``seq``:
    a restarted daemon numbers its messages, and its contacts, from 0 again, so its contact 0
    is not the old process's contact 0. A message whose ``seq`` is its source's last one
    again was recorded twice: scored once."""

    last: dict[str, int] = field(default_factory=dict)  # source -> last seq
    run: dict[str, int] = field(default_factory=dict)  # source -> its daemon run (0: the first)
    ids: dict[tuple[str, int, int], int] = field(default_factory=dict)  # (source, run, id) -> id scored
    restarts: int = 0
    twice: int = 0

    def new_message(self, payload: dict[str, Any]) -> bool:
        """Whether ``payload`` is to be scored (False: its source's last message again)."""
        seq = payload.get("seq")
        if not isinstance(seq, int) or isinstance(seq, bool):
            return True
        source = str(payload.get("source", ""))
        last = self.last.get(source)
        if last is not None and seq == last:
            self.twice += 1
            return False
        if last is not None and seq < last:
            self.restarts += 1
            self.run[source] = self.run.get(source, 0) + 1
        self.last[source] = seq
        return True

    def told_apart(self, payload: dict[str, Any], contacts: list[dict[str, Any]]) -> None:
        """Each contact's ``id`` one of its daemon run alone (unchanged while there is one run of one source)."""
        if not self.restarts and len(self.last) <= 1:
            return
        source = str(payload.get("source", ""))
        first = (source, self.run.get(source, 0)) == (next(iter(self.last)), 0)  # the first run heard: ids kept
        for c in contacts:
            key = (source, self.run.get(source, 0), int(c["id"]))
            c["id"] = self.ids.setdefault(key, int(c["id"]) if first else -1 - len(self.ids))  # (the daemon's are >= 0)


def read_frames(path: str, notes: list[str] | None = None) -> tuple[list[tuple[float, list[dict[str, Any]]]], int]:
    """The frames of ``path``, and how many lines of other topics (a ``cellbridge sub``
    recording) it skipped; what it found of restarted daemons and messages recorded twice
    goes to ``notes``."""
    frames: list[tuple[float, list[dict[str, Any]]]] = []
    other = 0
    runs = _Runs()
    for n, d in _lines(path):
        payload: dict[str, Any] | None = None
        if isinstance(d, dict) and "topic" in d and "t" not in d:  # a line of `cellbridge sub`
            if d["topic"] != "contact" or not isinstance(d.get("payload"), dict):
                other += 1
                continue
            payload = d["payload"]
            if not runs.new_message(payload):
                continue
            d = {"t": payload.get("t_sample"), "contacts": payload.get("contacts")}
        if not isinstance(d, dict):
            raise RunFileError(f"{path}:{n}: not a contact frame: not a JSON object")
        if not _finite(d.get("t")):
            raise RunFileError(f"{path}:{n}: not a contact frame: 't' is not a finite number")
        cs = d.get("contacts")
        if not isinstance(cs, list):
            raise RunFileError(f"{path}:{n}: not a contact frame: 'contacts' is not a list")
        for c in cs:
            problem = _contact_problem(c)
            if problem:
                raise RunFileError(f"{path}:{n}: not a contact frame: {problem}")
            if not c.get("missed", 0):
                _unnull(c)
        if payload is not None:
            runs.told_apart(payload, cs)
        if cs:  # what the scorer reads of each contact, no more: a long run's file is read in a fraction of its size
            frames.append((float(d["t"]), [{k: c[k] for k in SCORED if k in c} for c in cs]))
    if notes is not None and runs.restarts:
        times = "once" if runs.restarts == 1 else f"{runs.restarts} times"
        notes.append(f"{path}: the daemon restarted {times} (its seq went back): the contact ids of each run "
                     "told apart")
    elif notes is not None and len(runs.last) > 1:
        notes.append(f"{path}: contacts of {len(runs.last)} daemons (sources): their ids told apart")
    if notes is not None and runs.twice:
        notes.append(f"{path}: {runs.twice} message{'s' if runs.twice > 1 else ''} recorded twice "
                     "(the same seq again): scored once")
    return frames, other


def _digest(path: str) -> tuple[str, int]:
    """(SHA-256, lines) of a file."""
    h = hashlib.sha256()
    lines = 0
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
            lines += block.count(b"\n")
    return h.hexdigest(), lines


def read_run(directory: str) -> RunFiles:
    """The truths and frames of ``directory``, checked against its ``run.json`` when it has
    one (files of one run, whole or partial). Raises :class:`RunFileError` or ``OSError``."""
    if not os.path.isdir(directory):
        raise RunFileError(f"{directory}: no such directory (cellbridge robot run --out {directory} makes one)")
    meta: dict[str, Any] = {}
    notes: list[str] = []
    for name in (TRUTH, CONTACTS, RUN):  # a FIFO would be waited on for ever, a device read without end
        path = os.path.join(directory, name)
        if os.path.exists(path) and not stat.S_ISREG(os.stat(path).st_mode):
            raise RunFileError(f"{path}: not a regular file")
    run_path = os.path.join(directory, RUN)
    if os.path.exists(run_path):
        try:
            with open(run_path, encoding="utf-8") as fh:
                meta = json.load(fh)
        except ValueError as exc:
            raise RunFileError(f"{run_path}: not JSON: {exc}") from None
        files = meta.get("files") if isinstance(meta, dict) else None
        if not isinstance(files, dict) or meta.get("format") != FORMAT:
            raise RunFileError(f"{run_path}: not a run's description (format {FORMAT})")
        if not isinstance(meta.get("complete", True), bool):
            raise RunFileError(f"{run_path}: 'complete' is not true or false")
        for key in ("until", "busy", "idle", "virtual_s"):
            if key in meta and not _finite(meta[key]):
                raise RunFileError(f"{run_path}: '{key}' is not a finite number")
        for name in (TRUTH, CONTACTS):
            want = files.get(name, {}).get("sha256") if isinstance(files.get(name), dict) else None
            path = os.path.join(directory, name)
            if os.path.exists(path) and _digest(path)[0] != want:
                raise RunFileError(f"{path}: not the file this run wrote ({run_path} holds another SHA-256): "
                                   "files of two runs, or one changed since")
    else:
        notes.append(f"no {RUN} in {directory}: whether {TRUTH} and {CONTACTS} are of one run is not checked")
    truths, truth_lines = read_truths(os.path.join(directory, TRUTH))
    frames, other = read_frames(os.path.join(directory, CONTACTS), notes)
    if other:
        notes.append(f"{os.path.join(directory, CONTACTS)}: {other} lines of other topics skipped")
    if not truths:
        raise RunFileError(f"{os.path.join(directory, TRUTH)}: no true contact: nothing to score against")
    lo, hi = min(d["start"] for d in truths) - 1.0, max(d["end"] for d in truths) + 1.0
    if not meta and frames and not any(lo <= t <= hi for t, _ in frames):  # (run.json vouches for one run)
        raise RunFileError(f"{os.path.join(directory, CONTACTS)}: no frame within the true contacts' time "
                           f"({lo + 1:.3f} to {hi - 1:.3f} s; its frames {frames[0][0]:.3f} to {frames[-1][0]:.3f} s): "
                           "on another clock (a real-time recording's epoch?), or of another run")
    return RunFiles(truths, frames, meta, notes, truth_lines, os.path.join(directory, TRUTH))


def prepare_out(directory: str, force: bool = False) -> None:
    """Make ``directory`` (and check it takes files) before a run, so that a run of an
    hour does not end on an ``--out`` it cannot write, nor replace an earlier run's files
    unless ``force`` (``--force``). Raises :class:`RunFileError`."""
    try:
        os.makedirs(directory, exist_ok=True)
    except FileExistsError:
        raise RunFileError(f"--out {directory}: exists and is not a directory") from None
    except OSError as exc:
        raise RunFileError(f"--out {directory}: cannot make it: {exc.strerror or exc}") from None
    for name in (TRUTH, CONTACTS, RUN):
        path = os.path.join(directory, name)
        if os.path.lexists(path) and not os.path.isfile(path):
            raise RunFileError(f"--out {directory}: {path} is not a regular file (a directory?): the run could "
                               "not replace it")
    earlier = [name for name in (TRUTH, CONTACTS, RUN) if os.path.lexists(os.path.join(directory, name))]
    if earlier and not force:
        raise RunFileError(f"--out {directory}: holds an earlier run ({', '.join(earlier)}): choose another "
                           "directory, or add --force to replace it")
    probe = os.path.join(directory, f".{RUN}.probe")
    try:
        with open(probe, "w", encoding="utf-8") as fh:
            fh.write("{}\n")
        os.remove(probe)
    except OSError as exc:
        raise RunFileError(f"--out {directory}: cannot write in it: {exc.strerror or exc}") from None


def _plain(v: Any) -> Any:
    return v.item() if hasattr(v, "item") else str(v)


def write_run(directory: str, truths: list[dict[str, Any]], frames: list[tuple[float, list[dict[str, Any]]]],
              meta: dict[str, Any]) -> None:
    """Write the run's three files, each first as ``NAME.partial`` then renamed, ``run.json``
    last (with the others' SHA-256). On an error (a full disk) the ``.partial`` files are
    removed and nothing of this run is left looking whole; the error is raised."""
    written: list[str] = []
    try:
        old = os.path.join(directory, RUN)
        if os.path.exists(old):
            os.remove(old)  # the earlier run's: it vouches for files about to be replaced
        files = {}
        for name, lines in ((TRUTH, (json.dumps(d, default=_plain) for d in truths)),
                            (CONTACTS, (json.dumps({"t": t, "contacts": cs}, default=_plain) for t, cs in frames))):
            part = os.path.join(directory, name + ".partial")
            written.append(part)
            with open(part, "w", encoding="utf-8") as fh:
                for line in lines:
                    fh.write(line + "\n")
            digest, count = _digest(part)
            files[name] = {"sha256": digest, "lines": count}
        for name in (TRUTH, CONTACTS):
            os.replace(os.path.join(directory, name + ".partial"), os.path.join(directory, name))
        written.clear()
        part = os.path.join(directory, RUN + ".partial")
        written.append(part)
        with open(part, "w", encoding="utf-8") as fh:
            json.dump(dict(meta, format=FORMAT, files=files), fh, indent=1)
            fh.write("\n")
        os.replace(part, os.path.join(directory, RUN))
        written.clear()
    finally:
        for part in written:
            try:
                os.remove(part)
            except OSError:
                pass

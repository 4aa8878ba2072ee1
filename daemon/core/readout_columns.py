"""A READOUT record part as columns: from its payload bytes straight to numpy arrays.

The protocol's plain path (:func:`cellbridge.protocol.unpack_payload`) turns a READOUT
payload into a :class:`~cellbridge.protocol.Readout`: msgpack objects, packed again to
check the encoding is the canonical one, checked value by value, and a tuple per sample.
The daemon reads 22 gateways' records a hundred times a second and wants columns (bridge
ids, counts, flags) for its skin frames: building a Python object per sample, and then
walking them again to make the columns, is most of what a record costs it.

:func:`readout_columns` reads the canonical encoding of a current-version READOUT in one
compiled pass into :class:`ReadoutColumns`, and checks everything the plain path checks.
Its contract: on any payload it gives either None, or exactly what the plain path decodes
(:meth:`ReadoutColumns.readout` equals :func:`~cellbridge.protocol.unpack_payload`'s
message; the property tests hold it to this). It never rejects: whatever it does not
take as it is (an encoding it does not read, a value out of range, an index beyond
2**63 - 1) goes to the plain path, which decodes it or says why not, and counts it,
exactly as before.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from cellbridge.protocol import Mode, Readout, ReadoutSample
from numpy.typing import NDArray

__all__ = ["ReadoutColumns", "readout_columns"]

_MODES = tuple(Mode)
_NO_INT = -1  # (a value the compiled reader did not take as a canonical non-negative int)


@dataclass(slots=True, eq=False)  # (not frozen: a frozen dataclass's __init__ costs a µs more, a record)
class ReadoutColumns:
    """One READOUT record part (the fields of :class:`~cellbridge.protocol.Readout`) with
    its samples as one int64 array of rows (bridge, c1, c2, flags), and ``unchanged`` and
    ``missing`` as int64 arrays (each list strictly increasing, no bridge in two of the
    three). ``mode`` is the :class:`~cellbridge.protocol.Mode` value as an int. Read only:
    nothing changes a record once it is read."""

    index: int
    rate: int
    mode: int
    oversampling: int
    samples: NDArray[np.int64]  #: (n, 4): bridge, c1, c2, flags
    unchanged: NDArray[np.int64]
    missing: NDArray[np.int64]
    span_us: int = 0
    part: int = 0
    parts: int = 1
    root: int = 0
    age_us: int = 0

    @classmethod
    def of(cls, r: Readout) -> ReadoutColumns:
        """The columns of a plain record (one reassembled from fragments, or decoded by the
        plain path)."""
        s = np.array(r.samples, dtype=np.int64).reshape(len(r.samples), 4)
        return cls(r.index, r.rate, int(r.mode), r.oversampling, s, np.array(r.unchanged, dtype=np.int64),
                   np.array(r.missing, dtype=np.int64), r.span_us, r.part, r.parts, r.root, r.age_us)

    def readout(self) -> Readout:
        """The plain message these columns are of."""
        samples = tuple(ReadoutSample(*row) for row in self.samples.tolist())
        return Readout(self.index, self.rate, _MODES[self.mode], self.oversampling, samples,
                       tuple(self.unchanged.tolist()), tuple(self.missing.tolist()), self.span_us, self.part,
                       self.parts, self.root, self.age_us)


#: Whether the compiled reader is in use: False once it could not be compiled (or did not
#: read its warm-up record right), and every record then goes to the plain path, which
#: reads each the same, slower (numba retried a failed compile at every call: seconds a record).
_USABLE = [True]
#: Whether the compiled reader may be called: False from :func:`make_reader` until the end of
#: :func:`warm_up` (the daemon's warm-up compiles the reader meanwhile, in a child: a record
#: calling it then compiled it in the daemon's process, on the event loop), and the plain
#: path reads the records in between.
_READY = [True]


def readout_columns(payload: bytes) -> ReadoutColumns | None:
    """The record part of a current-version READOUT ``payload`` (the frame's payload bytes),
    or None: not the canonical encoding of a valid record as this reads it, or the compiled
    reader is not usable, or not yet (the plain path then decides). See the module."""
    return _read(payload) if _READY[0] else None


def _read(payload: bytes) -> ReadoutColumns | None:
    """:func:`readout_columns`, ready or not (the warm-up's read)."""
    if not _USABLE[0]:
        return None
    try:
        parse = _PARSE[0] if _PARSE else _compiled_parse()
        head, samples, unchanged, missing = parse(np.frombuffer(payload, dtype=np.uint8))
    except Exception:  # (the compile failed: compiled code itself raises nothing here)
        _USABLE[0] = False
        return None
    taken, k, rate, mode, over, span, part, parts, root, age = head.tolist()
    if not taken:
        return None
    return ReadoutColumns(k, rate, mode, over, samples, unchanged, missing, span, part, parts, root, age)


# -- the compiled reader ---------------------------------------------------------------------
# msgpack's canonical forms (what :func:`cellbridge.protocol.pack_payload` writes): a
# non-negative int in the smallest of fixint, uint8, 16, 32, 64; an array's length in the
# smallest of fixarray, array16, array32. Anything else is not read here.

def _be(buf: Any, at: int, k: int) -> Any:
    """The big-endian unsigned int of the ``k`` bytes at ``at`` (the caller checked they are
    there, and that 8 of them stay below 2**63)."""
    v = np.int64(0)
    for i in range(k):
        v = (v << 8) | np.int64(buf[at + i])
    return v


def _uint(buf: Any, pos: int) -> tuple[Any, Any]:
    """The canonical non-negative int at ``pos`` (at most 2**63 - 1) and the position after
    it; ``_NO_INT`` when there is none."""
    n = buf.shape[0]
    if pos >= n:
        return _NO_INT, pos
    b = np.int64(buf[pos])
    if b <= 0x7F:
        return b, pos + 1
    if b == 0xCC:
        if pos + 2 > n or buf[pos + 1] < 0x80:
            return _NO_INT, pos
        return np.int64(buf[pos + 1]), pos + 2
    if b == 0xCD:
        if pos + 3 > n:
            return _NO_INT, pos
        v = _be(buf, pos + 1, 2)
        return (v, pos + 3) if v > 0xFF else (_NO_INT, pos)
    if b == 0xCE:
        if pos + 5 > n:
            return _NO_INT, pos
        v = _be(buf, pos + 1, 4)
        return (v, pos + 5) if v > 0xFFFF else (_NO_INT, pos)
    if b == 0xCF:
        if pos + 9 > n or buf[pos + 1] >= 0x80:  # (beyond int64: the plain path's)
            return _NO_INT, pos
        v = _be(buf, pos + 1, 8)
        return (v, pos + 9) if v > 0xFFFF_FFFF else (_NO_INT, pos)
    return _NO_INT, pos


def _array(buf: Any, pos: int) -> tuple[Any, Any]:
    """The length of the canonical array header at ``pos`` and the position after it;
    ``_NO_INT`` when there is none."""
    n = buf.shape[0]
    if pos >= n:
        return _NO_INT, pos
    b = np.int64(buf[pos])
    if 0x90 <= b <= 0x9F:
        return b - 0x90, pos + 1
    if b == 0xDC:
        if pos + 3 > n:
            return _NO_INT, pos
        v = _be(buf, pos + 1, 2)
        return (v, pos + 3) if v >= 16 else (_NO_INT, pos)
    if b == 0xDD:
        if pos + 5 > n:
            return _NO_INT, pos
        v = _be(buf, pos + 1, 4)
        return (v, pos + 5) if v >= 0x10000 else (_NO_INT, pos)
    return _NO_INT, pos


def _ids(buf: Any, pos: int, out: Any) -> tuple[Any, Any]:
    """An array of strictly increasing bridge ids (0..65535) at ``pos`` into ``out``: how
    many (``_NO_INT``: not one) and the position after it."""
    k, pos = _array(buf, pos)
    if k < 0 or k > out.shape[0] or k > buf.shape[0] - pos:  # (an id takes a byte at least)
        return _NO_INT, pos
    last = -1
    for i in range(k):
        v, pos = _uint(buf, pos)
        if v <= last or v > 0xFFFF:  # (_NO_INT is below any id)
            return _NO_INT, pos
        out[i] = v
        last = v
    return k, pos


def _disjoint(a: Any, b: Any) -> bool:
    """Whether two strictly increasing arrays share no value."""
    i = j = 0
    while i < a.shape[0] and j < b.shape[0]:
        if a[i] == b[j]:
            return False
        if a[i] < b[j]:
            i += 1
        else:
            j += 1
    return True


def _parse(buf: Any) -> tuple[Any, Any, Any, Any]:
    """``head`` (taken (1) or not (0); index, rate, mode, oversampling, span, part, parts,
    root, age), the samples (n, 4), unchanged, missing."""
    head = np.zeros(10, dtype=np.int64)
    none = np.zeros((0, 4), dtype=np.int64)
    ids = np.zeros(0, dtype=np.int64)
    fields, pos = _array(buf, 0)
    if fields < 10 or fields > 12:
        return head, none, ids, ids
    k, pos = _uint(buf, pos)
    rate, pos = _uint(buf, pos)
    mode, pos = _uint(buf, pos)
    over, pos = _uint(buf, pos)
    if k < 0 or not 1 <= rate <= 0xFFFF or mode < 0 or mode > 1 or over < 0:
        return head, none, ids, ids
    if mode == 0:
        if over != 1:
            return head, none, ids, ids
        limit = 0xFFFF
    else:
        if not 1 <= over <= 0xFFFF:
            return head, none, ids, ids
        limit = 0xFF * over
    ns, pos = _array(buf, pos)
    if ns < 0 or 5 * ns > buf.shape[0] - pos:  # (a sample takes five bytes at least)
        return head, none, ids, ids
    samples = np.empty((ns, 4), dtype=np.int64)
    last = -1
    for i in range(ns):
        four, pos = _array(buf, pos)
        if four != 4:
            return head, none, ids, ids
        b, pos = _uint(buf, pos)
        c1, pos = _uint(buf, pos)
        c2, pos = _uint(buf, pos)
        fl, pos = _uint(buf, pos)
        if (b <= last or b > 0xFFFF or c1 < 0 or c1 > limit or c2 < 0 or c2 > limit
                or fl < 0 or fl > 0x03):
            return head, none, ids, ids
        samples[i, 0], samples[i, 1], samples[i, 2], samples[i, 3] = b, c1, c2, fl
        last = b
    room = np.empty(buf.shape[0], dtype=np.int64)
    nu, pos = _ids(buf, pos, room)
    if nu < 0:
        return head, none, ids, ids
    unchanged = room[:nu].copy()
    nm, pos = _ids(buf, pos, room)
    if nm < 0:
        return head, none, ids, ids
    missing = room[:nm].copy()
    span, pos = _uint(buf, pos)
    part, pos = _uint(buf, pos)
    parts, pos = _uint(buf, pos)
    root = age = 0
    if fields >= 11:
        root, pos = _uint(buf, pos)
        if not 0 <= root <= 0xFFFF:
            return head, none, ids, ids
    if fields == 12:
        age, pos = _uint(buf, pos)
        if not 1 <= age <= 0xFFFF_FFFF:
            return head, none, ids, ids
    if (pos != buf.shape[0] or not 0 <= span <= 0xFFFF_FFFF or not 1 <= parts <= 0xFF
            or not 0 <= part < parts):
        return head, none, ids, ids
    bridges = samples[:, 0]
    if not (_disjoint(bridges, unchanged) and _disjoint(bridges, missing) and _disjoint(unchanged, missing)):
        return head, none, ids, ids
    head[0], head[1], head[2], head[3], head[4] = 1, k, rate, mode, over
    head[5], head[6], head[7], head[8], head[9] = span, part, parts, root, age
    return head, samples, unchanged, missing


_PARSE: list[Any] = []  # the compiled _parse, made at the first record (or the warm-up): a tool
# importing the daemon's wire module does not import numba for it (0.2 s)


def make_reader() -> None:
    """The compiled reader's kernels made, not compiled (nor loaded): numba's cache can then be
    asked for them (:func:`cellbridge.tactile._jit.missing_from_cache`) before the warm-up.
    Until :func:`warm_up`, records are read by the plain path."""
    _READY[0] = False
    _compiled_parse()


def _compiled_parse() -> Any:
    """The compiled :func:`_parse` (its helpers compiled first: it calls them by name). Two
    callers at once (the daemon's warm-up thread and a first record) each compile what is
    not compiled yet, and the first parse made is the one kept."""
    if not _PARSE:
        from cellbridge.tactile._jit import compiled

        g = globals()
        for name in ("_be", "_uint", "_array", "_ids", "_disjoint"):
            f = g[name]  # (read once: a plain function, or another caller's compiled one)
            if not hasattr(f, "py_func"):
                g[name] = compiled(f)
        _PARSE.append(compiled(_parse))
    return _PARSE[0]


def warm_up() -> bool:
    """Compile the reader (or load it from the cache) by reading one small record: the
    daemon does it before its links start, so that its first READOUT does not hold the
    event loop for the compile (4 s on a fresh installation, 0.4 s from the cache).
    Whether the compiled reader is in use (False: it failed to compile, or misread the
    record, and is not used again: the plain path reads every record)."""
    from cellbridge.protocol.messages import pack_payload

    rec = Readout(1, 100, Mode.COUNTER, 1, (ReadoutSample(1, 2, 3, 0),), (2,), (3,), 10, 0, 1, 1, 1)
    try:
        got = _read(pack_payload(rec))
        if got is None or got.readout() != rec:
            _USABLE[0] = False
    finally:  # (records meanwhile were read by the plain path: none waited on the compile)
        _READY[0] = True
    return _USABLE[0]

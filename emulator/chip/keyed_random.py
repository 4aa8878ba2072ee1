"""Keyed, index-addressable random numbers for the chip model.

A chip's noise must be reproducible from (seed, channel, start cycle) alone: the
virtual-time mesh replays a run from its seed, and the same ``Chip.count`` call twice
must answer the same. It must also be *addressable*: the counter's fast path draws
only the random numbers near the gate's end, the per-cycle reference draws all of
them, and both must see the same values. Philox is a counter-based generator (the
output at a counter value depends on the key and that counter only), so a stream is
"seek to (key, counter), draw" — one state assignment (≈1 µs) instead of building a
generator per call (≈7 µs).

Normals come from numpy's ``Generator.standard_normal`` on Philox; numpy keeps that
stream stable across releases in practice but does not promise it, so a run is
reproducible for a seed on a given numpy version.

Normals are clipped to ±:data:`Z_MAX`. Clipping at 8σ changes no statistic anyone
can measure (P(|z| > 8) ≈ 1e-15) but bounds every jittered period, which is what lets
the counter's fast path prove that the synchroniser sees every edge.
"""

from __future__ import annotations

import enum
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

__all__ = ["Stream", "KeyedNormals", "GateNoise", "Z_MAX", "BLOCK_SIZE"]

Z_MAX = 8.0  #: normals are clipped to ±Z_MAX (in units of their sigma)

_MASK64 = (1 << 64) - 1
_SUBSTREAM_SHIFT = 32  # 2^32 Philox blocks (4 draws each) per substream: never exhausted
_TWO_M53 = 2.0**-53
BLOCK_SIZE = 128  #: periods per jitter block (the oscillator's BLOCK)


class Stream(enum.IntEnum):
    """What a random stream is for; part of the key, so streams never overlap."""

    JITTER_BLOCKS = 2  #: a gate's head: phase, per-block sums of the jitter, hint block's shape
    JITTER_STEPS = 3  #: period jitter within one block (substream = block index)
    ADC = 4  #: ADC input noise, one normal per conversion
    CRYSTAL = 5  #: a chip's crystal offset


class KeyedNormals:
    """Clipped standard normals and uniforms addressed by (stream, channel, cycle, substream).

    The chip seed and the start cycle form Philox's 128-bit key; stream, channel and
    substream go into its counter. Any (seed, channel, cycle) thus has its own
    independent sequence, and draws of any length are prefixes of one another.
    """

    def __init__(self, seed: int) -> None:
        if not isinstance(seed, (int, np.integer)):
            raise TypeError(f"seed must be an integer, got {seed!r}")
        self.seed = int(seed)
        self._seed64 = self.seed & _MASK64
        self._bitgen = np.random.Philox(key=0)
        self._gen = np.random.Generator(self._bitgen)
        # The state a seek assigns, in plain lists: the setter reads each word of a list
        # at half the cost of a numpy array's, and a store into a list costs a fraction
        # of one into an array (the seek runs twice a counter gate). An empty output
        # buffer (``buffer_pos`` 4): the next draw comes from the counter.
        self._counter = [0, 0, 0, 0]
        self._key = [self._seed64, 0]
        # (numpy's stubs type the state's words as arrays: the setter takes any sequence)
        self._state: Any = cast(Any, {"bit_generator": "Philox", "state": {"counter": self._counter, "key": self._key},
                                      "buffer": [0, 0, 0, 0], "buffer_pos": 4, "has_uint32": 0, "uinteger": 0})
        self._bitgen.state = self._state

    def _seek(self, stream: int, channel: int, cycle: int, substream: int) -> None:
        # Hot path (two per counter gate): plain int stores into kept lists, one setter.
        self._key[1] = cycle & _MASK64
        ctr = self._counter
        ctr[0] = (substream << _SUBSTREAM_SHIFT) & _MASK64
        ctr[1] = stream
        ctr[2] = channel & _MASK64
        self._bitgen.state = self._state

    def normals(
        self, stream: int, channel: int, cycle: int, n: int, substream: int = 0
    ) -> NDArray[np.float64]:
        """``n`` standard normals clipped to ±Z_MAX; a longer draw extends a shorter one."""
        self._seek(int(stream), channel, cycle, substream)
        z = self._gen.standard_normal(n)
        np.minimum(z, Z_MAX, out=z)
        return np.maximum(z, -Z_MAX, out=z)

    def gate_head(self, channel: int, cycle: int, n: int) -> tuple[float, NDArray[np.float64]]:
        """A gate's head draw (:data:`Stream.JITTER_BLOCKS`): (phase, ``n + BLOCK_SIZE``
        clipped normals), one seek and one draw. The hot path of every counter gate:
        :class:`GateNoise` and the chip's count both take it from here."""
        self._seek(_JITTER_BLOCKS, channel, cycle, 0)
        gen = self._gen
        phase = float(gen.random())
        z = gen.standard_normal(n + BLOCK_SIZE)
        np.minimum(z, Z_MAX, out=z)
        np.maximum(z, -Z_MAX, out=z)
        return phase, z

    def gate_heads(self, channel: int, cycles: list[int], out: NDArray[np.float64]) -> list[float]:
        """:meth:`gate_head` of the gates at ``cycles`` of one channel: the phases, and each
        gate's clipped normals in its row of ``out`` (rows of ``n + BLOCK_SIZE``). One draw
        per gate as there, clipped all at once: the same numbers."""
        gen = self._gen
        phases = []
        for k, cycle in enumerate(cycles):
            self._seek(_JITTER_BLOCKS, channel, cycle, 0)
            phases.append(float(gen.random()))
            gen.standard_normal(out=out[k])
        np.minimum(out, Z_MAX, out=out)
        np.maximum(out, -Z_MAX, out=out)
        return phases

    def uniform(self, stream: Stream, channel: int, cycle: int, substream: int = 0) -> float:
        """One uniform number in [0, 1) (a SplitMix64 hash of the key: no generator seek)."""
        tag = (int(stream) << 56) | ((substream & 0xFFFF) << 40) | (channel & 0xFFFFFFFFFF)
        h = _splitmix64(_splitmix64(cycle & _MASK64) ^ self._seed64 ^ tag)
        return (h >> 11) * _TWO_M53


_JITTER_BLOCKS = int(Stream.JITTER_BLOCKS)
_JITTER_STEPS = int(Stream.JITTER_STEPS)


class GateNoise:
    """The :class:`~cellbridge.emulator.chip.oscillator.JitterSource` of one gate: a chip's
    keyed normals at (channel, start cycle)."""

    __slots__ = ("_normals", "_channel", "_cycle")

    def __init__(self, normals: KeyedNormals, channel: int, cycle: int) -> None:
        self._normals = normals
        self._channel = channel
        self._cycle = cycle

    def head(self, n: int) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
        """(phase, n block sums, the hint block's BLOCK_SIZE shape normals): one seek, one draw."""
        phase, z = self._normals.gate_head(self._channel, self._cycle, n)
        return phase, z[:n], z[n:]

    def block_steps(self, b: int) -> NDArray[np.float64]:
        return self._normals.normals(_JITTER_STEPS, self._channel, self._cycle, BLOCK_SIZE, b)


def _splitmix64(x: int) -> int:
    """SplitMix64's output function: a bijective 64-bit mixer (Steele et al., 2014)."""
    x = (x + 0x9E3779B97F4A7C15) & _MASK64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _MASK64
    return x ^ (x >> 31)

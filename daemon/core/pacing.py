"""When the daemon's contact loop looks at the skin next: the estimate rate and the look gap.

Sans-I/O: fed the loop's times, it answers with the earliest time of the next look; the
service sleeps until then (or until data comes), and ``bench/bench_press_latency.py
--virtual`` runs the very same schedule in virtual time.

``[contact] rate`` bounds the *estimates* (each a skin-frame snapshot shipped to the
contact worker and fitted; a frame with nothing touched and no track left is not shipped,
so it is a look, not an estimate: counted, an idle event-based skin's frames, one per
period at their due times, kept the bucket empty at the frame rate, and a press's first
frame waited up to a period past its due), as a token bucket that holds ``BURST`` estimates: on average
at most ``rate`` a second, and an estimate that came late (a read or a tick in the way) does
not push the next one late too. With a rest of a whole period after each estimate, the
phase between the frames' due times and the estimates was whatever the first late one
left: every frame of a 100 Hz skin was then estimated 0-10 ms after it was due (3-5 ms on
average, on every press's first contact), until a frame came due later than the rest.

A look that finds no new frame costs a skin-frame computation: after one, the next comes
no sooner than ``empty_gap`` of the period or when the frame is due (a serial line read in
small pieces cost a look per read), or at the read that completes a skin frame
(``ContactScheduler.wakes``: that read is what the rest waits for). A look that finds the
frame due yet none taken (a transition holds it back) rests a whole period: no spinning.
"""

from __future__ import annotations

import math

#: Estimates the bucket holds: one late estimate may be followed by the next one sooner
#: than a period, never more.
BURST = 2.0
#: After a look that found no new frame, the next waits at least this fraction of the
#: estimate period, or until the frame is due (2.5 ms at 100 Hz).
EMPTY_LOOK_GAP = 0.25


class Pacer:
    """The contact loop's schedule at ``rate`` estimates a second (see the module)."""

    def __init__(self, rate: float, burst: float = BURST, empty_gap: float = EMPTY_LOOK_GAP) -> None:
        if not rate > 0 or not burst >= 1:
            raise ValueError(f"pacing needs rate > 0 and burst >= 1, got {rate} and {burst}")
        self.rate = rate
        self.burst = burst
        self.empty_gap = empty_gap
        self._tokens = burst
        self._at = -math.inf  # when _tokens was counted

    def set_rate(self, rate: float) -> None:
        """A reload changed ``[contact] rate``: from now on, this many a second."""
        if not rate > 0:
            raise ValueError(f"pacing needs rate > 0, got {rate}")
        self.rate = rate

    def _refill(self, now: float) -> None:
        if now > self._at:
            self._tokens = min(self.burst, self._tokens + (now - self._at) * self.rate)
            self._at = now

    def after_look(self, began: float, estimated: bool, due: float) -> float:
        """A look that began at ``began`` ran an estimate (``estimated``) or found nothing
        new; ``due``: when the next frame is there with no new data
        (:meth:`Pipeline.contact_due`, asked after the look). The earliest time of the next
        look (data coming earlier wakes the loop no sooner).

        The look is judged by when it began: a frame that came due while it ran (due after
        ``began``) is looked at again at once. Judged by its end, such a look "found the
        frame due yet none" and rested a whole period (+10 ms on a press's first contact)."""
        self._refill(began)
        if estimated:
            self._tokens -= 1.0
            return began + max(0.0, 1.0 - self._tokens) / self.rate
        if due <= began:  # due, yet none came (a transition holds it back): a period, no spinning
            return began + 1.0 / self.rate
        return min(began + self.empty_gap / self.rate, due)  # (at once when it came due meanwhile)

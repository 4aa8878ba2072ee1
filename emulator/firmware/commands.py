"""The bridge's measurement settings and the downlink commands that change them.

``execute`` is pure: command and current settings in, reply and (maybe) new settings
out, so every rule about what a value may be lives here and is tested once.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from cellbridge.emulator.firmware.reporting import ReportingMode
from cellbridge.protocol import Command, CommandReply, Mode, Op, Status

MIN_GATE = 1_000  #: 20 µs: fewer cycles leave too few edges to count
MAX_GATE = 5_000_000  #: 100 ms
MAX_OVERSAMPLING = 1024
ADC_CYCLES = 80  #: one charge-time conversion: discharge, 64 cycles to the sample, 8 SAR steps


@dataclass(frozen=True)
class Settings:
    rate_hz: int = 100
    mode: Mode = Mode.COUNTER
    gate_cycles: int = 100_000
    oversampling: int = 16
    reporting: ReportingMode = field(default_factory=ReportingMode)

    def measure_cycles(self) -> int:
        """Cycles one sample takes: C1 gate then C2 gate (or two ADC bursts)."""
        if self.mode is Mode.COUNTER:
            return 2 * self.gate_cycles
        return 2 * self.oversampling * ADC_CYCLES

    def max_rate(self, clock_hz: int) -> int:
        return clock_hz // self.measure_cycles()

    def period_cycles(self, clock_hz: int) -> int:
        return clock_hz // self.rate_hz

    def check(self, clock_hz: int) -> None:
        """ValueError naming the value when these settings cannot run: a sample's gates
        must fit its period (the limit the SET_ commands enforce, also at power-on)."""
        if type(self.rate_hz) is not int or not 1 <= self.rate_hz <= self.max_rate(clock_hz):
            raise ValueError(f"sampling rate {self.rate_hz!r} Hz: must be 1..{self.max_rate(clock_hz)} Hz "
                             f"(a sample takes {self.measure_cycles()} cycles at {clock_hz} Hz)")


def execute(cmd: Command, s: Settings, clock_hz: int, cycle: int,
            max_gate: int = MAX_GATE) -> tuple[CommandReply, Settings | None]:
    """Apply ``cmd``: (reply, new settings or None when nothing changes).

    ``max_gate`` is the longest gate whose counts the host can still unwrap
    (:func:`cellbridge.tactile.transfer.max_gate_cycles` of this chip): a longer one
    makes a press and a counter wrap look alike, so it is refused (BAD_VALUE)."""
    op, v = cmd.op, cmd.value

    def reply(status: Status, value: int | None = None) -> CommandReply:
        return CommandReply(cmd.token, op, status, value)

    if op is Op.PING:
        return reply(Status.OK, cycle), None
    if op is Op.RESET:
        return reply(Status.OK), None
    if v is None:
        return reply(Status.BAD_VALUE), None
    new: Settings
    if op is Op.SET_RATE:
        new = replace(s, rate_hz=v)
    elif op is Op.SET_MODE:
        if v not in (0, 1):
            return reply(Status.BAD_VALUE), None
        new = replace(s, mode=Mode(v))
    elif op is Op.SET_GATE:
        if not MIN_GATE <= v <= min(MAX_GATE, max_gate):
            return reply(Status.BAD_VALUE), None
        new = replace(s, gate_cycles=v)
    elif op is Op.SET_OVERSAMPLING:
        if not 1 <= v <= MAX_OVERSAMPLING:
            return reply(Status.BAD_VALUE), None
        new = replace(s, oversampling=v)
    elif op is Op.SET_REPORTING:
        try:
            new = replace(s, reporting=ReportingMode.from_value(v))
        except ValueError:
            return reply(Status.BAD_VALUE), None
    else:  # an op this firmware does not know
        return reply(Status.UNSUPPORTED), None
    if not 1 <= new.rate_hz <= new.max_rate(clock_hz):
        return reply(Status.BAD_VALUE), None  # the sampling schedule would not fit the gates
    return reply(Status.OK, v), new

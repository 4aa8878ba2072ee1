"""The daemon's TOML configuration: typed sections that give defaults, validation and ``--print-config``.

A daemon that runs for days must refuse a bad config at start with *every* problem
named (key and value), not die on the first one nor later at the first use of a
value. So each table is a frozen dataclass below (``[contact]`` is
:class:`ContactSection`, read as ``config.contact.rate``): the single place that lists
each key with its type, default, bound and meaning. :data:`SECTIONS` is derived from
them; :func:`load_config` reports all violations at once and :func:`default_toml`
prints the documented defaults. A key added to a section is checked, printed and
typed from that one line.
"""

from __future__ import annotations

import grp
import math
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from cellbridge.tactile import DEFAULT_NOISE

from cellbridge.errors import CellbridgeError

Check = Callable[[Any], str | None]  # returns a complaint, or None when the value is fine


class ConfigError(CellbridgeError, ValueError):
    """Every problem of a config, one per line, each naming the key and the value."""

    def __init__(self, source: str, problems: list[str]) -> None:
        self.problems = problems
        super().__init__(f"{source}: {len(problems)} problem(s) in the config:\n  " + "\n  ".join(problems))


@dataclass(frozen=True)
class Key:
    """One key of the schema, as validation and ``--print-config`` read it (made from a
    section field by :func:`_schema`)."""

    kind: type | tuple[type, ...]
    default: Any
    doc: str
    check: Check | None = None
    reloadable: bool = False  # SIGHUP applies it without a restart


def _one_of(*allowed: str) -> Check:
    return lambda v: None if v in allowed else f"must be one of {', '.join(map(repr, allowed))}"


def _endpoint(v: str) -> str | None:
    if v.startswith(("tcp://", "ipc://", "inproc://")) and len(v.split("://", 1)[1]) > 0:
        return None
    return "must be a ZeroMQ endpoint: tcp://HOST:PORT, ipc://PATH or inproc://NAME"


def _bits(v: int) -> str | None:
    return None if 16 <= v <= 64 else "must be in 16..64"


def _up_to(hi: float, *, lo: float = 0.0, open_lo: bool = True) -> Check:
    """A number in (lo, hi] (or [lo, hi]): every setting has an upper bound, so no value
    ``--check`` accepts can size a buffer or a timer beyond what the host has."""
    def check(v: Any) -> str | None:
        low_ok = v > lo if open_lo else v >= lo
        if math.isfinite(v) and low_ok and v <= hi:
            return None
        return f"must be in {'(' if open_lo else '['}{lo:g}, {hi:g}]"
    return check


def _count(lo: int, hi: int) -> Check:
    return lambda v: None if lo <= v <= hi else f"must be in {lo}..{hi}"


def _file_mode(v: int) -> str | None:
    return None if 0 <= v <= 0o777 else "must be permission bits in 0o000..0o777 (e.g. 0o660)"


def _group(v: str) -> str | None:
    if not v:
        return None
    try:
        grp.getgrnam(v)
    except KeyError:
        return "no such group on this host (create it, or leave empty for the daemon's own group)"
    return None


NUM = (int, float)

# The kind a key's TOML value must have, from its field's annotation: a float setting
# takes an integer too (``rate = 100``), a bool is never a number.
_KINDS: dict[str, type | tuple[type, ...]] = {"float": NUM, "int": int, "bool": bool, "str": str}


def _key(default: Any, doc: str, check: Check | None = None, *, reloadable: bool = False) -> Any:
    """A section field: its default, its meaning (``--print-config``), its bounds, and
    whether SIGHUP applies it without a restart. The field's annotation gives its kind."""
    return field(default=default, metadata={"doc": doc, "check": check, "reloadable": reloadable})


def _schema(cls: type) -> dict[str, Key]:
    """The :class:`Key` of every field of a section dataclass, in declaration order."""
    return {f.name: Key(_KINDS[str(f.type)], f.default, f.metadata["doc"], f.metadata["check"],
                        f.metadata["reloadable"]) for f in fields(cls)}


@dataclass(frozen=True)
class DaemonSection:
    """``[daemon]``: how the daemon logs."""

    log_level: str = _key("info", "stderr log level: debug, info, warning, error",
                          _one_of("debug", "info", "warning", "error"), reloadable=True)
    log_format: str = _key("json", "json (one object a line, for journald/log shippers) or text",
                           _one_of("json", "text"))


@dataclass(frozen=True)
class PubSection:
    """``[pub]``: the PUB socket every topic is published on."""

    endpoint: str = _key("tcp://127.0.0.1:5560", "where subscribers connect (tcp:// or ipc://)", _endpoint)
    hwm: int = _key(1000, "messages queued per subscriber before that subscriber loses messages",
                    _count(1, 1_000_000))
    source: str = _key("", "the daemon's name in every payload's source field (several daemons behind one "
                       "cellbridge proxy); empty: HOST:PORT, the host name and the endpoint's port")
    count_drops: bool = _key(False, "true: a message any subscriber has no room for is dropped for all and "
                             "counted in health; false: only that subscriber misses it (a gap in its seq)")
    ipc_mode: int = _key(0o666, "ipc:// endpoint only: permission bits of the socket file (0o666: any local "
                         "user may subscribe, as over loopback TCP; 0o660: ipc_group only)", _file_mode)
    ipc_group: str = _key("", "ipc:// endpoint only: group of the socket file (empty: the daemon's own)", _group)


@dataclass(frozen=True)
class ControlSection:
    """``[control]``: the control socket (status, tare, commands to bridges)."""

    endpoint: str = _key("tcp://127.0.0.1:5561", "control requests (ROUTER; clients use REQ or DEALER)",
                         _endpoint)
    command_timeout: float = _key(1.0, "s to wait for bridges to answer a command", _up_to(60), reloadable=True)
    max_request_bytes: int = _key(65536, "largest request answered; a larger one gets an error reply, one "
                                  "over 4 times this is refused by the transport (the connection is dropped)",
                                  _count(1024, 1 << 24))
    max_pending: int = _key(256, "requests in progress at once (commands wait for bridges); more are "
                            "answered 'busy' at once", _count(1, 65536))
    ipc_mode: int = _key(0o660, "ipc:// endpoint only: permission bits of the socket file (0o660: the "
                         "daemon's user and ipc_group may control the skin)", _file_mode)
    ipc_group: str = _key("", "ipc:// endpoint only: group of the socket file, whose members may connect "
                          "(empty: the daemon's own group)", _group)


@dataclass(frozen=True)
class PeersSection:
    """``[peers]``: what connected peers may hold (descriptors, handshakes)."""

    handshake_timeout: float = _key(2.0, "s a connection may take to complete its ZeroMQ (and CURVE) handshake "
                                    "before it is dropped: idle connects cost a descriptor only this long",
                                    _up_to(60))
    max_pub: int = _key(256, "connections the PUB socket holds at once (subscribers); more are closed at "
                        "once and counted", _count(1, 16384))
    max_control: int = _key(64, "connections the control socket holds at once; more are closed at once "
                            "and counted", _count(1, 16384))
    max_per_address: int = _key(64, "connections one peer address (an IP; the user id for ipc://) may hold "
                                "on each socket; on loopback every local client shares one address",
                                _count(1, 16384))
    fd_reserve: int = _key(64, "descriptors kept beyond the peers' for the links, capture files, the "
                           "contact worker and ZeroMQ itself; the daemon refuses to start when its descriptor "
                           "limit cannot hold peers + reserve", _count(16, 65536))


@dataclass(frozen=True)
class LayoutSection:
    """``[layout]``: where the elements sit."""

    file: str = _key("", "skin layout TOML (see docs/contacts.md); empty: geometry from the bridges' HELLO",
                     reloadable=True)


@dataclass(frozen=True)
class ChipSection:
    """``[chip]``: what is assumed of a bridge until it says otherwise."""

    clock_hz: float = _key(50e6, "nominal bridge clock when a bridge has not said (HELLO)", _up_to(1e9))
    gate_cycles: int = _key(100_000, "counter gate until a SET_GATE is acknowledged", _count(1, 1 << 32))
    cycle_bits: int = _key(64, "width of the bridges' cycle counter (wrap-around)", _bits)


@dataclass(frozen=True)
class CalibrationSection:
    """``[calibration]``: baselines, drift tracking and touch thresholds."""

    n_baseline: int = _key(50, "quiet readings per element before its baseline is set (memory: elements "
                           "x this x 16 bytes)", _count(1, 10_000), reloadable=True)
    enter: float = _key(50e-15, "F; ΔC above which an element counts as touched", _up_to(1e-9, open_lo=False),
                        reloadable=True)
    leave: float = _key(25e-15, "F; every channel below this: released", _up_to(1e-9, open_lo=False),
                        reloadable=True)
    k_enter: float = _key(8.0, "touch threshold in noise sigmas, if larger than enter",
                          _up_to(1000, open_lo=False), reloadable=True)
    k_leave: float = _key(4.0, "release threshold in noise sigmas", _up_to(1000, open_lo=False), reloadable=True)
    holdoff: float = _key(2.0, "s after release before drift tracking resumes", _up_to(3600, open_lo=False),
                          reloadable=True)
    tau: float = _key(10.0, "s, drift tracker time constant (untouched elements only)", _up_to(86400),
                      reloadable=True)
    tau_negative: float = _key(3.0, "s, tracker time constant while the reading is below baseline",
                               _up_to(86400), reloadable=True)
    max_drift: float = _key(1e-15, "F/s, fastest drift of one element followed; a press rising faster is "
                            "reported, not absorbed", _up_to(1e-9), reloadable=True)
    max_touch: float = _key(600.0, "s an element may stay touched before it is re-baselined (counted, named "
                            "on contact) unless its reading is still a contact's (a held press is kept, "
                            "looked at again after as long); "
                            "0: never", _up_to(1e7, open_lo=False), reloadable=True)
    max_step_rate: float = _key(250.0, "Hz, most baseline/touch updates a second (each on every element's "
                                "newest reading); the gate limit of the bridges is enough", _up_to(10_000),
                                reloadable=True)


@dataclass(frozen=True)
class InverseSection:
    """``[inverse]``: the per-element (ΔC1, ΔC2) → (F, S) inverse."""

    noise: float = _key(DEFAULT_NOISE, "F, rms noise of one ΔC reading (weights the inverse and contact fit)",
                        _up_to(1e-9), reloadable=True)


@dataclass(frozen=True)
class ContactSection:
    """``[contact]``: contact estimation and tracking."""

    enabled: bool = _key(True, "estimate contacts (topic contact)", reloadable=True)
    rate: float = _key(100.0, "Hz, at most this many estimates a second on average (one late estimate may be "
                       "followed by the next sooner, on its frame's time), each on the newest consistent moment; "
                       "frames with nothing touched and no contact left are not estimated and do not count",
                       _up_to(1000), reloadable=True)
    method: str = _key("capacitance", "model fit in capacitance (default) or area space",
                       _one_of("capacitance", "area"), reloadable=True)
    birth_frames: int = _key(1, "estimates a contact must persist before it is reported (with a stable id); "
                             "1: at once (a touch needs 8 noise sigmas), more to ride out impulsive noise, "
                             "each costing one sample period of latency",
                             _count(1, 1000), reloadable=True)
    max_missed: int = _key(2, "estimates a reported contact may be missing before it ends", _count(0, 1000),
                           reloadable=True)
    worker_timeout: float = _key(30.0, "s one estimate may take before the worker process is taken as hung, "
                                 "killed and replaced", _up_to(3600), reloadable=True)
    max_lag: float = _key(0.5, "s the DATA readings of a bridge on no readout schedule (booting, without mesh "
                          "time, an old capture) may trail the newest and still hold a frame estimated on DATA "
                          "alone back; a bridge later than that is unknown for the newer frames (listed in the "
                          "contact message's unknown) and named in health layout.late", _up_to(10), reloadable=True)
    max_lag_readings: int = _key(128, "DATA readings kept per element for frames estimated on DATA (memory: "
                                 "elements x this x 42 bytes); max_lag reaches back at most this many readings "
                                 "at calibration.max_step_rate", _count(1, 4096), reloadable=True)


@dataclass(frozen=True)
class FramesSection:
    """``[frames]``: skin frames from the gateways' readout records."""

    margin: float = _key(0.02, "s a skin frame waits past its readout and its record's serial time for a "
                         "gateway's record before it is estimated without it (that gateway's elements unknown); "
                         "covers the host's read and scheduling delays. Frames whose records all came are "
                         "estimated at once", _up_to(10, open_lo=False), reloadable=True)
    max_pending: int = _key(64, "skin frames waiting for records at most (a newer one sends the oldest out as "
                            "it is)", _count(1, 100_000), reloadable=True)


@dataclass(frozen=True)
class HealthSection:
    """``[health]``: the health topic and when a bridge counts as silent, stuck or gone."""

    interval: float = _key(1.0, "s between health messages (and topology change checks)", _up_to(3600),
                           reloadable=True)
    bridge_timeout: float = _key(2.0, "s without data before a bridge is reported silent", _up_to(3600),
                                 reloadable=True)
    stuck_after: float = _key(2.0, "s a channel may repeat one raw value before it is reported stuck",
                              _up_to(86400), reloadable=True)
    forget_after: float = _key(600.0, "s of silence after which a bridge the layout does not place is "
                               "forgotten (placed bridges stay reported silent)", _up_to(86400), reloadable=True)


@dataclass(frozen=True)
class ProtocolSection:
    """``[protocol]``: duplicate removal and reassembly on the host."""

    dedupe_window: int = _key(256, "sequence numbers remembered per bridge for duplicate removal",
                              lambda v: None if 1 <= v < 32768 else "must be in 1..32767")
    reassembly_timeout: float = _key(2.0, "s a fragmented datagram may take to complete", _up_to(60))


@dataclass(frozen=True)
class LinkConfig:
    """One ``[[link]]``: a gateway's serial line (or a capture replayed as one)."""

    name: str = _key("", "name used in health and logs (default: link0, link1, ...)")
    url: str = _key("", "pyserial URL: /dev/ttyUSB0, a pty path, socket://HOST:PORT; or replay:FILE")
    baudrate: int = _key(1_000_000, "serial line speed (ignored by ptys and sockets)", _count(1, 100_000_000))
    capture: str = _key("", "record this link's raw bytes (with arrival times) to this file")
    replay_speed: float = _key(1.0, "replay: links: 1 = recorded speed, 0 = as fast as possible",
                               _up_to(1e6, open_lo=False))
    replay_clock: str = _key("shifted", "replay: links: host times shifted to now, or as recorded",
                             _one_of("shifted", "recorded"))
    wait_for_subscriber: bool = _key(False, "replay: links: start once a subscriber is connected")
    exit_when_done: bool = _key(False, "replay: links: stop the daemon (exit 0) when the replay ends")
    reconnect_min: float = _key(0.1, "s, first reconnect delay (doubles up to reconnect_max)", _up_to(3600))
    reconnect_max: float = _key(5.0, "s, longest reconnect delay", _up_to(3600))

    @property
    def is_replay(self) -> bool:
        return self.url.startswith("replay:")


#: The section dataclass of each top-level table, in ``--print-config`` order.
SECTION_TYPES: dict[str, type] = {
    "daemon": DaemonSection, "pub": PubSection, "control": ControlSection, "peers": PeersSection,
    "layout": LayoutSection, "chip": ChipSection, "calibration": CalibrationSection, "inverse": InverseSection,
    "contact": ContactSection, "frames": FramesSection, "health": HealthSection, "protocol": ProtocolSection,
}
#: Every key of every section (kind, default, doc, bounds, reloadable), from the dataclasses.
SECTIONS: dict[str, dict[str, Key]] = {name: _schema(cls) for name, cls in SECTION_TYPES.items()}
LINK_KEYS: dict[str, Key] = _schema(LinkConfig)


@dataclass(frozen=True)
class Config:
    """A validated config: one typed section per table (``config.contact.rate``), the
    links, and the raw ``[security]`` table (read by :mod:`cellbridge.daemon.ops.security`).

    Build it with :func:`parse_config` or :func:`load_config`, which check every bound;
    the defaults of a section are its dataclass's (``ContactSection()``)."""

    daemon: DaemonSection = field(default_factory=DaemonSection)
    pub: PubSection = field(default_factory=PubSection)
    control: ControlSection = field(default_factory=ControlSection)
    peers: PeersSection = field(default_factory=PeersSection)
    layout: LayoutSection = field(default_factory=LayoutSection)
    chip: ChipSection = field(default_factory=ChipSection)
    calibration: CalibrationSection = field(default_factory=CalibrationSection)
    inverse: InverseSection = field(default_factory=InverseSection)
    contact: ContactSection = field(default_factory=ContactSection)
    frames: FramesSection = field(default_factory=FramesSection)
    health: HealthSection = field(default_factory=HealthSection)
    protocol: ProtocolSection = field(default_factory=ProtocolSection)
    links: tuple[LinkConfig, ...] = ()
    security: dict[str, Any] | None = None
    source: str = "defaults"
    base_dir: Path = field(default_factory=Path.cwd)

    def layout_path(self) -> Path | None:
        f = self.layout.file
        return None if not f else (self.base_dir / f)

    def needs_restart(self, new: Config) -> list[str]:
        """The settings that differ in ``new`` and that only a restart applies
        (``section.key``, and ``link`` for any change of the links)."""
        fixed = [f"{name}.{key}" for name, keys in SECTIONS.items() for key, spec in keys.items()
                 if not spec.reloadable and getattr(getattr(new, name), key) != getattr(getattr(self, name), key)]
        if new.links != self.links:
            fixed.append("link")
        return fixed


def _type_ok(value: Any, kind: type | tuple[type, ...]) -> bool:
    if isinstance(value, bool) and kind is not bool:
        return False
    return isinstance(value, kind)


def _kind_name(kind: type | tuple[type, ...]) -> str:
    names: dict[type | tuple[type, ...], str] = {bool: "true or false", int: "an integer", str: "a string"}
    return "a number" if kind == NUM else names[kind]


def _table(where: str, raw: Mapping[str, Any], schema: dict[str, Key], problems: list[str]) -> dict[str, Any]:
    out = {k: spec.default for k, spec in schema.items()}
    for key, value in raw.items():
        spec = schema.get(key)
        name = f"{where}.{key}"
        if spec is None:
            problems.append(f"{name}: unknown key (known: {', '.join(schema)})")
            continue
        if not _type_ok(value, spec.kind):
            problems.append(f"{name} = {value!r}: must be {_kind_name(spec.kind)}")
            continue
        complaint = spec.check(value) if spec.check else None
        if complaint:
            problems.append(f"{name} = {value!r}: {complaint}")
            continue
        out[key] = float(value) if spec.kind == NUM else value
    return out


def parse_config(data: Mapping[str, Any], source: str = "config", base_dir: Path | None = None) -> Config:
    """Validate a parsed TOML document into a :class:`Config`; :class:`ConfigError`
    lists every problem (unknown sections and keys, wrong kinds, values out of bounds)."""
    problems: list[str] = []
    sections: dict[str, Any] = {}
    known = set(SECTIONS) | {"link", "security"}
    for name in data:
        if name not in known:
            problems.append(f"[{name}]: unknown section (known: {', '.join(sorted(known))})")
    for name, schema in SECTIONS.items():
        raw = data.get(name, {})
        if not isinstance(raw, Mapping):
            problems.append(f"[{name}] must be a table")
            raw = {}
        sections[name] = SECTION_TYPES[name](**_table(name, raw, schema, problems))
    links = []
    raw_links = data.get("link", [])
    if not isinstance(raw_links, list):
        problems.append("link must be an array of tables: [[link]]")
        raw_links = []
    for i, raw in enumerate(raw_links):
        if not isinstance(raw, Mapping):
            problems.append(f"link[{i}] must be a table")
            continue
        t = _table(f"link[{i}]", raw, LINK_KEYS, problems)
        t["name"] = t["name"] or f"link{i}"
        if base_dir is not None:  # files named in the config are relative to it
            if t["url"].startswith("replay:"):
                t["url"] = "replay:" + str(base_dir / t["url"][len("replay:"):])
            if t["capture"]:
                t["capture"] = str(base_dir / t["capture"])
        link = LinkConfig(**t)
        if not link.url:
            problems.append(f"link[{i}].url: missing (a device path, socket://HOST:PORT or replay:FILE)")
        if link.reconnect_max < link.reconnect_min:
            problems.append(f"link[{i}].reconnect_max = {link.reconnect_max!r}: must be >= reconnect_min")
        links.append(link)
    # A replay in recorded time puts the daemon on the recording's clock; a link on another
    # clock (a line's host time, a replay shifted to now) beside it cannot share it.
    if any(ln.is_replay and ln.replay_clock == "recorded" for ln in links):
        for i, ln in enumerate(links):
            if not (ln.is_replay and ln.replay_clock == "recorded"):
                what = "a replay shifted to now" if ln.is_replay else "a line read on the host's clock"
                problems.append(f"link[{i}] ({ln.name!r}) is {what}, beside a replay with replay_clock = "
                                f"\"recorded\", which runs the daemon on the recording's clock: replay every "
                                f"link in recorded time, or none")
    names = [ln.name for ln in links]
    for dup in sorted({n for n in names if names.count(n) > 1}):
        problems.append(f"link name {dup!r} used twice")
    cal: CalibrationSection = sections["calibration"]
    if cal.leave > cal.enter:
        problems.append(f"calibration.leave = {cal.leave!r}: must not exceed calibration.enter")
    if cal.k_leave > cal.k_enter:
        problems.append(f"calibration.k_leave = {cal.k_leave!r}: must not exceed calibration.k_enter")
    if sections["pub"].endpoint == sections["control"].endpoint:
        problems.append("pub.endpoint and control.endpoint must differ")
    security = data.get("security")
    if security is not None and not isinstance(security, Mapping):
        problems.append("[security] must be a table")
    if problems:
        raise ConfigError(source, problems)
    return Config(**sections, links=tuple(links), security=dict(security) if security else None, source=source,
                  base_dir=base_dir if base_dir is not None else Path.cwd())


def load_config(path: str | Path) -> Config:
    """Read and validate a config file; paths inside it are relative to the file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(p), [f"cannot read: {exc.strerror}"]) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(p), [f"not valid TOML: {exc}"]) from None
    except RecursionError:  # tomllib parses nested arrays and tables recursively
        raise ConfigError(str(p), ["not valid TOML: nested too deeply"]) from None
    return parse_config(data, str(p), p.resolve().parent)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(v)


def default_toml() -> str:
    """The defaults as a commented config file (``cellbridge daemon --print-config``)."""
    lines = ["# cellbridge daemon configuration: every key with its default.",
             "# Keys marked (reload) take effect on SIGHUP; the others need a restart.", ""]
    for name, schema in SECTIONS.items():
        lines.append(f"[{name}]")
        for key, spec in schema.items():
            mark = " (reload)" if spec.reloadable else ""
            value = f"0o{spec.default:03o}" if spec.check is _file_mode else _toml_value(spec.default)
            lines.append(f"{key} = {value}    # {spec.doc}{mark}")
        lines.append("")
    lines += ["# One [[link]] per gateway (at least one). Example:", "[[link]]"]
    example = {"name": "gw0", "url": "/dev/ttyUSB0"}
    for key, spec in LINK_KEYS.items():
        lines.append(f"{key} = {_toml_value(example.get(key, spec.default))}    # {spec.doc}")
    lines += ["", "# [security]: CURVE keys for binding beyond loopback (see docs/zmq-api.md, Security)."]
    return "\n".join(lines) + "\n"

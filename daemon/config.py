"""The daemon's TOML configuration: one schema gives defaults, validation and ``--print-config``.

A daemon that runs for days must refuse a bad config at start with *every* problem
named (key and value), not die on the first one nor later at the first use of a
value. So the schema below is the single place that lists each key with its type,
default, check and meaning; :func:`load_config` reports all violations at once and
:func:`default_toml` prints the documented defaults.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cellbridge.errors import CellbridgeError
from cellbridge.tactile import DEFAULT_NOISE

Check = Callable[[Any], str | None]  # returns a complaint, or None when the value is fine


class ConfigError(CellbridgeError, ValueError):
    """Every problem of a config, one per line, each naming the key and the value."""

    def __init__(self, source: str, problems: list[str]) -> None:
        self.problems = problems
        super().__init__(f"{source}: {len(problems)} problem(s) in the config:\n  " + "\n  ".join(problems))


@dataclass(frozen=True)
class Key:
    kind: type | tuple[type, ...]
    default: Any
    doc: str
    check: Check | None = None
    reloadable: bool = False  # SIGHUP applies it without a restart


def _positive(v: Any) -> str | None:
    return None if math.isfinite(v) and v > 0 else "must be > 0"


def _non_negative(v: Any) -> str | None:
    return None if math.isfinite(v) and v >= 0 else "must be >= 0"


def _one_of(*allowed: str) -> Check:
    return lambda v: None if v in allowed else f"must be one of {', '.join(map(repr, allowed))}"


def _endpoint(v: str) -> str | None:
    if v.startswith(("tcp://", "ipc://", "inproc://")) and len(v.split("://", 1)[1]) > 0:
        return None
    return "must be a ZeroMQ endpoint: tcp://HOST:PORT, ipc://PATH or inproc://NAME"


def _bits(v: int) -> str | None:
    return None if 16 <= v <= 64 else "must be in 16..64"


NUM = (int, float)

SECTIONS: dict[str, dict[str, Key]] = {
    "daemon": {
        "log_level": Key(str, "info", "stderr log level: debug, info, warning, error",
                         _one_of("debug", "info", "warning", "error"), reloadable=True),
        "log_format": Key(str, "json", "json (one object a line, for journald/log shippers) or text",
                          _one_of("json", "text")),
    },
    "pub": {
        "endpoint": Key(str, "tcp://127.0.0.1:5560", "where subscribers connect (tcp:// or ipc://)", _endpoint),
        "hwm": Key(int, 1000, "messages queued per subscriber before that subscriber loses messages",
                   lambda v: None if v >= 1 else "must be >= 1"),
        "count_drops": Key(bool, False, "true: a message any subscriber has no room for is dropped for all and "
                           "counted in health; false: only that subscriber misses it (a gap in its seq)"),
    },
    "control": {
        "endpoint": Key(str, "tcp://127.0.0.1:5561", "control requests (ROUTER; clients use REQ or DEALER)",
                        _endpoint),
        "command_timeout": Key(NUM, 1.0, "s to wait for bridges to answer a command", _positive, reloadable=True),
    },
    "layout": {
        "file": Key(str, "", "skin layout TOML (see docs/contacts.md); empty: geometry from the bridges' HELLO",
                    reloadable=True),
    },
    "chip": {
        "clock_hz": Key(NUM, 50e6, "nominal bridge clock when a bridge has not said (HELLO)", _positive),
        "gate_cycles": Key(int, 100_000, "counter gate until a SET_GATE is acknowledged",
                           lambda v: None if v >= 1 else "must be >= 1"),
        "cycle_bits": Key(int, 64, "width of the bridges' cycle counter (wrap-around)", _bits),
    },
    "calibration": {
        "n_baseline": Key(int, 50, "quiet readings per element before its baseline is set",
                          lambda v: None if v >= 1 else "must be >= 1", reloadable=True),
        "enter": Key(NUM, 50e-15, "F; ΔC above which an element counts as touched", _non_negative, reloadable=True),
        "leave": Key(NUM, 25e-15, "F; every channel below this: released", _non_negative, reloadable=True),
        "k_enter": Key(NUM, 8.0, "touch threshold in noise sigmas, if larger than enter", _non_negative,
                       reloadable=True),
        "k_leave": Key(NUM, 4.0, "release threshold in noise sigmas", _non_negative, reloadable=True),
        "holdoff": Key(NUM, 2.0, "s after release before drift tracking resumes", _non_negative, reloadable=True),
        "tau": Key(NUM, 10.0, "s, drift tracker time constant (untouched elements only)", _positive,
                   reloadable=True),
        "tau_negative": Key(NUM, 3.0, "s, tracker time constant while the reading is below baseline", _positive,
                            reloadable=True),
        "max_drift": Key(NUM, 1e-15, "F/s, fastest drift of one element followed; a press rising faster is "
                         "reported, not absorbed", _positive, reloadable=True),
        "max_touch": Key(NUM, 600.0, "s an element may stay touched before it is re-baselined (and counted); "
                         "0: never", _non_negative, reloadable=True),
        "max_step_rate": Key(NUM, 250.0, "Hz, most baseline/touch updates a second (each on every element's "
                             "newest reading); the gate limit of the bridges is enough", _positive, reloadable=True),
    },
    "inverse": {
        "noise": Key(NUM, DEFAULT_NOISE, "F, rms noise of one ΔC reading (weights the inverse and contact fit)",
                     _positive, reloadable=True),
    },
    "contact": {
        "enabled": Key(bool, True, "estimate contacts (topic contact)", reloadable=True),
        "rate": Key(NUM, 100.0, "Hz, at most this many estimates a second, each on the newest consistent moment", _positive,
                    reloadable=True),
        "method": Key(str, "capacitance", "model fit in capacitance (default) or area space",
                      _one_of("capacitance", "area"), reloadable=True),
        "birth_frames": Key(int, 3, "estimates a contact must persist before it is reported (with a stable id)",
                            lambda v: None if v >= 1 else "must be >= 1", reloadable=True),
        "max_missed": Key(int, 2, "estimates a reported contact may be missing before it ends",
                          lambda v: None if v >= 0 else "must be >= 0", reloadable=True),
        "worker_timeout": Key(NUM, 30.0, "s one estimate may take before the worker process is taken as hung, "
                              "killed and replaced", _positive, reloadable=True),
        "max_lag": Key(NUM, 0.5, "s a bridge's data may trail the newest and still hold the estimated moment "
                       "back (contacts are estimated on one moment of the skin); a bridge later than that "
                       "contributes its newest reading and is named in health layout.late", _positive,
                       reloadable=True),
    },
    "health": {
        "interval": Key(NUM, 1.0, "s between health messages (and topology change checks)", _positive,
                        reloadable=True),
        "bridge_timeout": Key(NUM, 2.0, "s without data before a bridge is reported silent", _positive,
                              reloadable=True),
        "stuck_after": Key(NUM, 2.0, "s a channel may repeat one raw value before it is reported stuck",
                           _positive, reloadable=True),
        "forget_after": Key(NUM, 600.0, "s of silence after which a bridge the layout does not place is "
                            "forgotten (placed bridges stay reported silent)", _positive, reloadable=True),
    },
    "protocol": {
        "dedupe_window": Key(int, 256, "sequence numbers remembered per bridge for duplicate removal",
                             lambda v: None if 1 <= v < 32768 else "must be in 1..32767"),
        "reassembly_timeout": Key(NUM, 2.0, "s a fragmented datagram may take to complete", _positive),
    },
}

LINK_KEYS: dict[str, Key] = {
    "name": Key(str, "", "name used in health and logs (default: link0, link1, ...)"),
    "url": Key(str, "", "pyserial URL: /dev/ttyUSB0, a pty path, socket://HOST:PORT; or replay:FILE"),
    "baudrate": Key(int, 1_000_000, "serial line speed (ignored by ptys and sockets)",
                    lambda v: None if v > 0 else "must be > 0"),
    "capture": Key(str, "", "record this link's raw bytes (with arrival times) to this file"),
    "replay_speed": Key(NUM, 1.0, "replay: links: 1 = recorded speed, 0 = as fast as possible", _non_negative),
    "replay_clock": Key(str, "shifted", "replay: links: host times shifted to now, or as recorded",
                        _one_of("shifted", "recorded")),
    "wait_for_subscriber": Key(bool, False, "replay: links: start once a subscriber is connected"),
    "exit_when_done": Key(bool, False, "replay: links: stop the daemon (exit 0) when the replay ends"),
    "reconnect_min": Key(NUM, 0.1, "s, first reconnect delay (doubles up to reconnect_max)", _positive),
    "reconnect_max": Key(NUM, 5.0, "s, longest reconnect delay", _positive),
}


@dataclass(frozen=True)
class LinkConfig:
    name: str
    url: str
    baudrate: int = 1_000_000
    capture: str = ""
    replay_speed: float = 1.0
    replay_clock: str = "shifted"
    wait_for_subscriber: bool = False
    exit_when_done: bool = False
    reconnect_min: float = 0.1
    reconnect_max: float = 5.0

    @property
    def is_replay(self) -> bool:
        return self.url.startswith("replay:")


@dataclass(frozen=True)
class Config:
    """A validated config: ``sections[name][key]`` plus the links and the raw ``[security]`` table."""

    sections: dict[str, dict[str, Any]]
    links: tuple[LinkConfig, ...]
    security: dict[str, Any] | None = None
    source: str = "defaults"
    base_dir: Path = field(default_factory=Path.cwd)

    def __getitem__(self, section: str) -> dict[str, Any]:
        return self.sections[section]

    def layout_path(self) -> Path | None:
        f = self.sections["layout"]["file"]
        return None if not f else (self.base_dir / f)


def _type_ok(value: Any, kind: type | tuple[type, ...]) -> bool:
    if isinstance(value, bool) and kind is not bool:
        return False
    return isinstance(value, kind)


def _kind_name(kind: type | tuple[type, ...]) -> str:
    return "a number" if kind == NUM else {bool: "true or false", int: "an integer", str: "a string"}[kind]


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
    """Validate a parsed TOML document; :class:`ConfigError` lists every problem."""
    problems: list[str] = []
    sections: dict[str, dict[str, Any]] = {}
    known = set(SECTIONS) | {"link", "security"}
    for name in data:
        if name not in known:
            problems.append(f"[{name}]: unknown section (known: {', '.join(sorted(known))})")
    for name, schema in SECTIONS.items():
        raw = data.get(name, {})
        if not isinstance(raw, Mapping):
            problems.append(f"[{name}] must be a table")
            raw = {}
        sections[name] = _table(name, raw, schema, problems)
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
        if not t["url"]:
            problems.append(f"link[{i}].url: missing (a device path, socket://HOST:PORT or replay:FILE)")
        if t["reconnect_max"] < t["reconnect_min"]:
            problems.append(f"link[{i}].reconnect_max = {t['reconnect_max']!r}: must be >= reconnect_min")
        links.append(LinkConfig(**t))
    names = [ln.name for ln in links]
    for dup in sorted({n for n in names if names.count(n) > 1}):
        problems.append(f"link name {dup!r} used twice")
    cal = sections["calibration"]
    if cal["leave"] > cal["enter"]:
        problems.append(f"calibration.leave = {cal['leave']!r}: must not exceed calibration.enter")
    if cal["k_leave"] > cal["k_enter"]:
        problems.append(f"calibration.k_leave = {cal['k_leave']!r}: must not exceed calibration.k_enter")
    if sections["pub"]["endpoint"] == sections["control"]["endpoint"]:
        problems.append("pub.endpoint and control.endpoint must differ")
    security = data.get("security")
    if security is not None and not isinstance(security, Mapping):
        problems.append("[security] must be a table")
    if problems:
        raise ConfigError(source, problems)
    return Config(sections, tuple(links), dict(security) if security else None, source,
                  base_dir if base_dir is not None else Path.cwd())


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
            lines.append(f"{key} = {_toml_value(spec.default)}    # {spec.doc}{mark}")
        lines.append("")
    lines += ["# One [[link]] per gateway (at least one). Example:", "[[link]]"]
    example = {"name": "gw0", "url": "/dev/ttyUSB0"}
    for key, spec in LINK_KEYS.items():
        lines.append(f"{key} = {_toml_value(example.get(key, spec.default))}    # {spec.doc}")
    lines += ["", "# [security]: CURVE keys for binding beyond loopback (see docs/zmq-api.md, Security)."]
    return "\n".join(lines) + "\n"

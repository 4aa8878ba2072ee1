"""The daemon's config: defaults, every bad key named at once, --print-config round trip."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, cast

import pytest
from cellbridge.daemon.core.config import LINK_KEYS, SECTIONS, ConfigError, default_toml, load_config, parse_config


def test_defaults_are_valid_and_documented() -> None:
    cfg = parse_config({"link": [{"url": "/dev/ttyUSB0"}]})
    assert cfg.pub.endpoint == "tcp://127.0.0.1:5560"
    assert cfg.control.endpoint == "tcp://127.0.0.1:5561"
    assert cfg.links[0].name == "link0"
    for section, keys in SECTIONS.items():
        for key, spec in keys.items():
            assert spec.doc, f"{section}.{key} has no doc"


def test_every_problem_is_named_at_once() -> None:
    bad = {
        "pub": {"endpoint": "localhost:5560", "hwm": 0, "colour": "red"},
        "calibration": {"tau": -1.0, "n_baseline": "many"},
        "contact": {"method": "guess"},
        "nonsense": {},
        "link": [{"name": "a"}, {"name": "a", "url": "x", "replay_speed": -2}],
    }
    with pytest.raises(ConfigError) as exc:
        parse_config(bad, "my.toml")
    text = str(exc.value)
    for needle in ("pub.endpoint = 'localhost:5560'", "pub.hwm = 0", "pub.colour: unknown key",
                   "calibration.tau = -1.0", "calibration.n_baseline = 'many': must be an integer",
                   "contact.method = 'guess'", "[nonsense]: unknown section", "link[0].url: missing",
                   "link[1].replay_speed = -2", "link name 'a' used twice", "my.toml"):
        assert needle in text, needle
    assert len(exc.value.problems) == 10


def test_bool_is_not_a_number() -> None:
    with pytest.raises(ConfigError, match="health.interval = True"):
        parse_config({"health": {"interval": True}})


def test_print_config_parses_back_to_the_defaults(tmp_path: Path) -> None:
    text = default_toml()
    data = tomllib.loads(text)
    cfg = parse_config(data)
    for section, keys in SECTIONS.items():
        for key, spec in keys.items():
            assert getattr(getattr(cfg, section), key) == spec.default
    f = tmp_path / "d.toml"
    f.write_text(text)
    assert load_config(f).links[0].url == "/dev/ttyUSB0"


def test_missing_file_and_bad_toml(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "nope.toml")
    f = tmp_path / "bad.toml"
    f.write_text("[pub\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(f)


def test_layout_path_is_relative_to_the_config(tmp_path: Path) -> None:
    f = tmp_path / "d.toml"
    f.write_text('[layout]\nfile = "skin.toml"\n[[link]]\nurl = "/dev/null"\n')
    assert load_config(f).layout_path() == tmp_path.resolve() / "skin.toml"


def test_cli_print_config_check_and_errors(tmp_path: Path) -> None:
    import subprocess

    from daemon_harness import CLI

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([CLI, "daemon", *args], capture_output=True, text=True, timeout=60)

    help_text = run("--help").stdout
    assert "--print-config" in help_text and "replay:FILE" in help_text and "docs/zmq-api.md" in help_text
    printed = run("--print-config")
    assert printed.returncode == 0
    cfg = tmp_path / "c.toml"
    cfg.write_text(printed.stdout)
    ok = run("--config", str(cfg), "--check")
    assert ok.returncode == 0 and "ok (1 link(s))" in ok.stdout
    cfg.write_text(printed.stdout.replace('hwm = 1000', 'hwm = "lots"').replace("[layout]\nfile = \"\"",
                                                                              "[layout]\nfile = \"nope.toml\""))
    bad = run("--config", str(cfg), "--check")
    assert bad.returncode == 2 and "pub.hwm = 'lots': must be an integer" in bad.stderr
    cfg.write_text(printed.stdout.replace("[layout]\nfile = \"\"", "[layout]\nfile = \"nope.toml\""))
    bad = run("--config", str(cfg), "--check")
    assert bad.returncode == 2 and "nope.toml" in bad.stderr and "cannot read layout" in bad.stderr
    assert run().returncode == 2


def test_max_lag_that_would_take_gigabytes_is_refused() -> None:
    """max_lag = 3600 passed --check and sized a buffer of 37 GB on a 32x32 skin."""
    with pytest.raises(ConfigError, match=r"contact.max_lag = 3600"):
        parse_config({"contact": {"max_lag": 3600}})


def test_every_number_has_an_upper_bound() -> None:
    """Every size-like (and every other numeric) setting is bounded: a value a thousand
    times beyond any sane one is refused, never sized into memory or a timer."""
    unbounded = []
    tables = [*((s, k, {s: {k: 10**15}}) for s, keys in SECTIONS.items() for k in keys),
              *(("link", k, {"link": [{"url": "/dev/ttyUSB0", k: 10**15}]}) for k in LINK_KEYS)]
    for section, key, data in tables:
        spec = (SECTIONS[section] if section in SECTIONS else LINK_KEYS)[key]
        if spec.kind is bool or spec.kind is str:
            continue
        try:
            parse_config(cast(dict[str, Any], data))  # a table of one section or of one link
        except ConfigError:
            continue
        unbounded.append(f"{section}.{key}")
    assert not unbounded


def test_the_fallback_readings_buffer_is_sized_in_readings() -> None:
    """The longest max_lag at the fastest step rate still keeps at most max_lag_readings per element."""
    from cellbridge.daemon.core.pipeline import Pipeline
    from cellbridge.tactile import grid_layout

    cfg = parse_config({"contact": {"max_lag": 10.0, "max_lag_readings": 256},
                        "calibration": {"max_step_rate": 1000.0}})
    layout = grid_layout(32, 32)
    p = Pipeline(cfg, layout)
    assert p.skin.readings is not None and p.skin.readings.depth <= 256 + 8
    assert p.skin.readings.t.nbytes <= layout.n * (256 + 8) * 8


def test_sections_are_typed_frozen_and_the_only_way_in() -> None:
    """Settings are read as ``config.contact.rate``: each table a frozen dataclass whose
    fields are exactly the schema's keys, each value of its declared type; no dict access."""
    import dataclasses

    from cellbridge.daemon.core.config import SECTION_TYPES, Config, ContactSection

    cfg = parse_config({"contact": {"rate": 50, "max_lag": 1}, "link": [{"url": "/dev/ttyUSB0"}]})
    assert cfg.contact.rate == 50.0 and isinstance(cfg.contact.rate, float)  # an integer in TOML, a float here
    assert isinstance(cfg.contact.max_lag, float) and cfg.contact.birth_frames == 1
    assert isinstance(cfg.contact, ContactSection)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.contact.rate = 1.0  # type: ignore[misc]  # the point: a validated config cannot be changed
    with pytest.raises(TypeError):
        cfg["contact"]  # type: ignore[index]  # the point: no string lookups
    assert list(SECTION_TYPES) == list(SECTIONS)
    kinds = {"bool": bool, "int": int, "str": str, "float": float}  # the annotations, as strings
    for name, cls in SECTION_TYPES.items():
        section = getattr(cfg, name)
        assert type(section) is cls and dataclasses.is_dataclass(section)
        assert [f.name for f in dataclasses.fields(cls)] == list(SECTIONS[name])
        for f in dataclasses.fields(cls):
            assert type(getattr(section, f.name)) is kinds[str(f.type)], f"{name}.{f.name}"
    assert Config().contact == ContactSection()  # a section's defaults are its dataclass's


def test_a_reload_names_exactly_the_changed_settings_that_need_a_restart() -> None:
    old = parse_config({"link": [{"url": "/dev/ttyUSB0"}]})
    new = parse_config({"pub": {"hwm": 5}, "contact": {"rate": 50.0}, "daemon": {"log_level": "debug"},
                        "link": [{"url": "/dev/ttyUSB1"}]})
    assert old.needs_restart(new) == ["pub.hwm", "link"]  # contact.rate and the log level: reloadable
    assert old.needs_restart(parse_config({"link": [{"url": "/dev/ttyUSB0"}]})) == []


@pytest.mark.parametrize("other", [{"url": "/dev/ttyUSB0"}, {"url": "socket://127.0.0.1:9"},
                                   {"url": "replay:b.cbcap", "replay_clock": "shifted"}])
def test_a_replay_in_recorded_time_takes_no_link_on_another_clock(other: dict[str, Any]) -> None:
    """A replay in recorded time puts the whole daemon on the recording's clock: a line
    read beside it (host monotonic time) or a replay shifted to now was accepted, and its
    reads, seconds since boot, were taken as the recording's time (health t_host in
    1970, the clock stepping back at every read of one and forward at every read of the other)."""
    data = {"link": [{"name": "a", "url": "replay:a.cbcap", "replay_clock": "recorded"}, {"name": "b", **other}]}
    with pytest.raises(ConfigError, match="recorded") as exc:
        parse_config(data, "t")
    assert "link[1]" in str(exc.value), str(exc.value)


def test_replays_in_recorded_time_together_are_accepted() -> None:
    data = {"link": [{"name": n, "url": f"replay:{n}.cbcap", "replay_clock": "recorded"} for n in ("a", "b")]}
    assert len(parse_config(data, "t").links) == 2

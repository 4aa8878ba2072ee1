"""The service and the offline driver are one daemon: a golden corpus scenario replayed
through the real :class:`~cellbridge.daemon.shell.service.Service` (asyncio, its links, its
contact loop, ZeroMQ on ``inproc://``) publishes what :class:`~cellbridge.daemon.shell.offline.OfflineDaemon`
publishes on the same reads, the driver that makes the corpus's ``.chk`` files.

The service replays in recorded time at half the recorded speed; the contact rate is set above the
frame rate, so neither driver's pacing holds an estimate back and both look at every
frame the reads complete. Element messages are compared one for one; contact messages by
the frame they estimate (the service's loop may take a newer frame when a read came first,
as it is meant to): the frames both estimated must give the same contacts.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import zmq
import zmq.asyncio
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.shell.capture import write_capture
from cellbridge.daemon.shell.contact_worker import InlineExecutor
from cellbridge.daemon.shell.offline import OfflineDaemon
from cellbridge.daemon.shell.service import Service

from support.golden_corpus import BASE_CONFIG, DATA, SCENARIOS, same_values, serial_reads
from support.service_messages import service_messages
from support.shell_fakes import RecordingHooks

SCENARIO = "multihop_line"  # a 3 N press on a line of 6 bridges: contacts from frames of 5 hops


def _config(recording: Path, links: list[str], endpoint: str, *, scenario: str = SCENARIO,
            speed: float = 0.5) -> dict[str, Any]:
    sc = next(s for s in SCENARIOS if s.name == scenario)
    data: dict[str, Any] = {k: dict(v) for k, v in BASE_CONFIG.items()}
    for k, v in sc.config.items():
        data.setdefault(k, {}).update(v)
    data["contact"]["rate"] = 1000.0  # above the frame rate: pacing holds neither driver back
    data["pub"] = {"endpoint": endpoint}
    data["control"] = {"endpoint": endpoint + "-ctl"}
    # the replay waits for the test's subscriber: a message published before its subscription
    # reached the service would be lost to it, not to the comparison's other side
    data["link"] = [{"name": n, "url": f"replay:{recording}", "replay_speed": speed, "replay_clock": "recorded",
                     "exit_when_done": True, "wait_for_subscriber": True} for n in links]
    return data


def _service_messages(recording: Path, links: list[str], topics: tuple[str, ...] = ("element", "contact"),
                      ) -> list[tuple[str, dict[str, Any]]]:
    """What the service published on ``inproc://``, in order, while it replayed ``recording``."""
    endpoint = "inproc://service-offline"
    return _run_service(_config(recording, links, endpoint), endpoint, topics)


def _run_service(data: dict[str, Any], endpoint: str, topics: tuple[str, ...]) -> list[tuple[str, dict[str, Any]]]:
    """What a service of config ``data`` (replays that exit when done, publishing on
    ``endpoint``) published on ``topics``, in order."""

    def make(ctx: zmq.asyncio.Context) -> Service:
        cfg = parse_config(data, "test")
        return Service(cfg, hooks=RecordingHooks(cfg), ctx=ctx, contact_executor=InlineExecutor)

    return service_messages(make, endpoint, topics)


def _comparable(payload: dict[str, Any]) -> dict[str, Any]:
    """A message without its sequence number (each topic's count starts where its first
    subscriber came) and its ``source`` (the publisher's stamp); its values are compared
    by :func:`same_values` (floats to 1e-9 relative: capacitances are 1e-11 F, so a
    rounding to decimal places would have compared none of them)."""
    return {k: v for k, v in payload.items() if k not in ("seq", "source")}


def _frame_key(message: dict[str, Any]) -> float:
    return round(message["t_sample"], 6)


def test_the_service_publishes_what_the_offline_driver_publishes_on_a_corpus_recording() -> None:
    recording = DATA / f"{SCENARIO}.mcap"
    reads = serial_reads(recording)
    links = sorted({link for link, _, _ in reads})
    offline = OfflineDaemon(parse_config(_config(recording, links, "inproc://unused"), "test"),
                            topics={"element", "contact"}, recorded=True)
    want = [(o.topic, _comparable(o.payload)) for o in offline.run(sorted((t, link, d) for link, t, d in reads))
            if o.topic in ("element", "contact")]
    got = [(topic, _comparable(p)) for topic, p in _service_messages(recording, links)]

    assert not same_values([p for t, p in got if t == "element"], [p for t, p in want if t == "element"], "element")
    offline_contacts = {_frame_key(p): p for t, p in want if t == "contact"}
    service_contacts = [p for t, p in got if t == "contact"]
    assert sum(1 for p in offline_contacts.values() if p["contacts"]) >= 10  # the press was seen
    # The same frame estimated by both gives the same contacts, ids included. What the loop
    # decides is the event loop's: when it looks (a read that came meanwhile makes it take
    # the newer frame: the service skips a frame the offline driver, whose reads are never
    # late, estimated), so the instant of the look (``t_host``, each contact's ``t``) and
    # what a track's history counts (``age``, ``missed``; a birth or an end a frame apart)
    # are left out, a contact one of them has not yet born or already ended is not
    # compared, and a frame only one of them estimated neither.
    compared = 0
    for mine in service_contacts:
        theirs = offline_contacts.get(_frame_key(mine))
        if theirs is None:  # a frame only the service took (the offline look came after a newer read)
            continue
        assert not same_values(_frame_fields(mine), _frame_fields(theirs)), mine["t_sample"]
        a, b = _by_id(mine), _by_id(theirs)
        for cid in a.keys() & b.keys():
            assert not same_values(a[cid], b[cid]), (mine["t_sample"], cid, sorted(a), sorted(b))
            compared += 1
        assert len(a.keys() ^ b.keys()) <= 1, (mine["t_sample"], sorted(a), sorted(b))
    assert compared >= 0.5 * sum(len(p["contacts"]) for p in offline_contacts.values()), compared
    assert len(service_contacts) >= 0.5 * len(offline_contacts), (len(service_contacts), len(offline_contacts))


#: What a contact owes to the loop's history rather than to its frame.
HISTORY = ("t", "age", "missed")


def _frame_fields(message: dict[str, Any]) -> dict[str, Any]:
    """A contact message's fields other than its contacts and the instant of its look."""
    return {k: v for k, v in message.items() if k not in ("t_host", "contacts")}


def _by_id(message: dict[str, Any]) -> dict[int, dict[str, Any]]:
    return {c["id"]: {k: v for k, v in c.items() if k not in HISTORY} for c in message["contacts"]}


def test_a_replay_in_recorded_time_runs_on_the_recordings_clock() -> None:
    """Ticked on today's wall clock, every bridge of a recording made earlier was reported
    silent (and then forgotten) while its reads were still being replayed."""
    recording = DATA / f"{SCENARIO}.mcap"
    reads = serial_reads(recording)
    links = sorted({link for link, _, _ in reads})
    first, last = min(t for _, t, _ in reads), max(t for _, t, _ in reads)
    got = _service_messages(recording, links, ("health", "topology"))
    health = [p for t, p in got if t == "health"]
    assert len(health) >= 3, len(health)
    for h in health:
        assert first <= h["t_host"] <= last, (h["t_host"], first, last)  # on the recording's clock
        bridges = h["bridges"]
        silent = [b.get("id") for b in (bridges.values() if isinstance(bridges, dict) else bridges) if b["silent"]]
        assert not silent, (h["t_host"] - first, silent)
        for name in links:
            since = h["links"][name]["connected_since"]
            assert since is None or first <= since <= last, since  # the link came up at the first read


def _silent(health: dict[str, Any]) -> list[str]:
    bridges = health["bridges"]
    items = bridges.items() if isinstance(bridges, dict) else enumerate(bridges)
    return sorted(str(k) for k, b in items if b["silent"])


def _two_links_3s_apart(tmp_path: Path, name: str, speed: float) -> tuple[list[tuple[float, str, bytes]], dict[str, Any], str]:
    """The two_gateways scenario's captures with the second line up 3 s after the first
    (5.5 s of recording), replayed in recorded time at ``speed``: the reads merged in time
    order, the config, and its endpoint (``inproc://name``)."""
    sc = next(s for s in SCENARIOS if s.name == "two_gateways")
    merged: list[tuple[float, str, bytes]] = []
    for link, shift in (("gw1", 0.0), ("gw9", 3.0)):
        recs = [(t + shift, d) for n, t, d in serial_reads(DATA / "two_gateways.mcap") if n == link]
        write_capture(tmp_path / f"{link}.cbcap", recs)
        merged += [(t, link, d) for t, d in recs]
    merged.sort(key=lambda r: r[0])
    data: dict[str, Any] = {k: dict(v) for k, v in BASE_CONFIG.items()}
    for k, v in sc.config.items():
        data.setdefault(k, {}).update(v)
    endpoint = f"inproc://{name}"
    data["pub"] = {"endpoint": endpoint}
    data["control"] = {"endpoint": endpoint + "-ctl"}
    data["link"] = [{"name": n, "url": f"replay:{tmp_path / n}.cbcap", "replay_speed": speed,
                     "replay_clock": "recorded", "exit_when_done": True, "wait_for_subscriber": True}
                    for n in ("gw1", "gw9")]
    return merged, data, endpoint


def test_two_links_replayed_in_recorded_time_keep_one_clock(tmp_path: Path) -> None:
    """Two gateways' captures, the second line up 3 s after the first (its records 3 s
    later): replayed, each link was paced from its own first record, so the second line's
    t+3 s came at once, the recording's clock jumped 3 s and the first line's bridges were
    reported silent while their reads were being replayed. The offline driver, fed the
    same reads in time order, reports none silent."""
    merged, data, endpoint = _two_links_3s_apart(tmp_path, "two-links-recorded", 2.0)
    offline = OfflineDaemon(parse_config(data, "test"), topics={"health"}, recorded=True)
    assert not [o.payload["t_host"] for o in offline.run(merged) if o.topic == "health" and _silent(o.payload)]
    got = _run_service(data, endpoint, ("health",))
    health = [p for t, p in got if t == "health"]
    t0 = merged[0][0]
    gw1_end = max(t for t, link, _ in merged if link == "gw1")
    quiet = data["health"].get("bridge_timeout", 2.0) if "health" in data else 2.0
    during = [h for h in health if h["t_host"] < gw1_end + quiet - 0.05]
    assert len(during) >= 3, [h["t_host"] - t0 for h in health]
    assert not [(round(h["t_host"] - t0, 2), _silent(h)) for h in during if _silent(h)]
    # the first line really went quiet at its end: on the recording's clock, it is silent
    after = [h for h in health if h["t_host"] > gw1_end + quiet + 0.05]
    assert after and all(_silent(h) for h in after), [(h["t_host"] - t0, _silent(h)) for h in health]


def test_a_replay_in_recorded_time_ticks_on_the_recordings_clock_as_the_offline_driver(tmp_path: Path) -> None:
    """Health of a replay in recorded time goes out at the recording's times, those of the
    offline driver fed the same reads, whatever pace the loop keeps: ticked by the loop's
    timer only, a replay the machine could not keep pace with came in bursts between two
    ticks, and health went out at whichever read was last fed (2.4 s of recording apart
    beside four CPU burners, where the recording asks for one a second)."""
    # flat out: the whole recording in bursts, far faster than the loop's 0.1 s timer
    merged, data, endpoint = _two_links_3s_apart(tmp_path, "recorded-ticks", 0.0)
    offline = OfflineDaemon(parse_config(data, "test"), topics={"health"}, recorded=True)
    want = [o.payload["t_host"] for o in offline.run(merged) if o.topic == "health"]
    got = [p["t_host"] for t, p in _run_service(data, endpoint, ("health",)) if t == "health"]
    end = merged[-1][0] - 0.5  # (after the last read the loop's own ticks go on at its time)
    assert len([t for t in want if t < end]) >= 3
    assert [t for t in got if t < end] == [t for t in want if t < end]


def test_a_recorded_replay_with_absurd_times_ticks_a_bounded_number_of_times(tmp_path: Path) -> None:
    """A capture whose times jump an hour, to 1e308 s (a corrupt double) and to NaN: the
    ticks of the recording's clock before each read are bounded (the last 100 of a gap), a
    time where a tick adds nothing ends them, and the replay runs to its end."""
    reads = [(t, d) for _, t, d in serial_reads(DATA / f"{SCENARIO}.mcap")]
    reads.insert(60, (reads[59][0] + 3600.0, reads[60][1]))
    reads.insert(120, (1e308, reads[120][1]))
    reads.insert(150, (math.nan, reads[150][1]))
    write_capture(tmp_path / "gw1.cbcap", reads)
    data: dict[str, Any] = {k: dict(v) for k, v in BASE_CONFIG.items()}
    endpoint = "inproc://recorded-absurd"
    data["pub"] = {"endpoint": endpoint}
    data["control"] = {"endpoint": endpoint + "-ctl"}
    data["link"] = [{"name": "gw1", "url": f"replay:{tmp_path / 'gw1.cbcap'}", "replay_speed": 0.0,
                     "replay_clock": "recorded", "exit_when_done": True, "wait_for_subscriber": True}]
    t0 = time.monotonic()
    health = [p for t, p in _run_service(data, endpoint, ("health",)) if t == "health"]
    assert time.monotonic() - t0 < 60
    assert len(health) >= 2


def test_a_recording_that_steps_back_a_day_goes_on_on_its_clock(tmp_path: Path) -> None:
    """Two days' captures appended in the wrong order (the second a day earlier): the
    recording's clock was held at its newest time, so it stood still at the first day's
    end for the whole second day (no health, no silence, no command deadline); and the
    link fed the whole second day at once. Now the clock follows the step back (the
    pipeline takes it as a host clock stepping back) and the second day is paced."""
    reads = [(t, d) for _, t, d in serial_reads(DATA / f"{SCENARIO}.mcap")]
    day = 86400.0
    write_capture(tmp_path / "two-days.cbcap", reads + [(t - day, d) for t, d in reads])
    endpoint = "inproc://recorded-step-back"
    data: dict[str, Any] = {k: dict(v) for k, v in BASE_CONFIG.items()}
    data["pub"] = {"endpoint": endpoint}
    data["control"] = {"endpoint": endpoint + "-ctl"}
    data["link"] = [{"name": "gw1", "url": f"replay:{tmp_path / 'two-days.cbcap'}", "replay_speed": 2.0,
                     "replay_clock": "recorded", "exit_when_done": True, "wait_for_subscriber": True}]
    health = [p for t, p in _run_service(data, endpoint, ("health",)) if t == "health"]
    first, last = reads[0][0] - day, reads[-1][0] - day
    second = [h["t_host"] - first for h in health if first <= h["t_host"] < last - 0.2]
    assert len(second) >= 2, [h["t_host"] - reads[0][0] for h in health]


def test_two_gateways_replayed_flat_out_publish_the_offline_drivers_element_messages() -> None:
    """Two links of one recording, flat out: each link fed 64 records at a turn, so the
    element stages saw one gateway's frames long before the other's of the same time (403
    of 406 element messages differed from the offline driver's, and no contact was ever
    estimated); then reads of one time came in whichever order the links' tasks ran (274
    differed). In one time order, ties by link name as the offline driver sorts them, they
    are the same messages."""
    recording = DATA / "two_gateways.mcap"
    reads = serial_reads(recording)
    links = sorted({link for link, _, _ in reads})
    assert len(links) == 2
    endpoint = "inproc://two-gateways-flat-out"
    data = _config(recording, links, endpoint, scenario="two_gateways", speed=0.0)
    offline = OfflineDaemon(parse_config(data, "test"), topics={"element", "contact"}, recorded=True)
    want = [_comparable(o.payload) for o in offline.run(sorted((t, link, d) for link, t, d in reads))
            if o.topic == "element"]
    got = _run_service(data, endpoint, ("element", "contact"))
    elements = [_comparable(p) for t, p in got if t == "element"]
    assert len(elements) == len(want) > 300
    assert not same_values(elements, want, "element")[:5]
    assert any(p["contacts"] for t, p in got if t == "contact")  # the press was estimated

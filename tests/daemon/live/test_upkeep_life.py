"""The upkeep through a robot's life, offline: motion that cannot tell two sensors apart,
restarts that must lose nothing, and chains of events (two swaps, a swap during a creep, a
full disk when a write is due). The scans are the emulator's own (mechanism_scans), fed
to :class:`Upkeep` a second at a time as the recorder feeds it, its record kept in a real
state file where a test restarts it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from loopcal.calibration.parameters import INDEX
from loopcal.daemon.config.controller import load_controller_config, write_initial_config
from loopcal.daemon.live.upkeep import Upkeep
from loopcal.daemon.live.upkeep_state import state_path
from loopcal.simulator.drift import OffsetDrift
from loopcal.simulator.offline import mechanism_scans
from loopcal.simulator.phases import Phases
from loopcal.simulator.scenarios import HandMoves
from loopcal.simulator.task import TaskLoop
from tests.support.disk import can_mount, fill, small_tmpfs
from tests.support.processes import loopcal_main
from tests.support.rows import rows_from
from tests.support.sessions import calibrated_config, truth_for

RATE = 20
#: a task loop of two waypoints that cannot tell sensor 3 from sensor 4 (their patterns
#: correlate 0.9998 over it): seed 1
AMBIGUOUS = dict(seed=1, waypoints=2)


class Events(list):
    """The upkeep's emit: (s of scans fed, kind, message, details)."""

    clock = 0.0

    def __call__(self, kind, level, message, **details):
        self.append((self.clock, kind, message, details))

    def of(self, kind: str) -> list:
        return [e for e in self if e[1] == kind]

    def kinds(self) -> list[str]:
        return [e[1] for e in self]


def scans(seed: int, seconds: float, motion, drifts=()) -> tuple[np.ndarray, np.ndarray]:
    truth = truth_for(seed)
    t_us, codes = mechanism_scans(
        motion, truth, int(seconds * RATE), seed=seed, drifts=tuple(drifts)
    )
    return truth, rows_from(t_us, codes)


def upkeep(config: Path, mode: str = "write", state: Path | None = None) -> Upkeep:
    return Upkeep(
        load_controller_config(config),
        Events(),
        mode=mode,
        target_mm=0.05,
        threshold_mm=0.1,
        min_interval_s=600.0,
        threaded=False,
        state=state,
    )


def feed(up: Upkeep, rows: np.ndarray, *, follow: Path | None = None) -> None:
    """A second at a time; ``follow``: reload the config when it changes, as the recorder
    does within 2 s."""
    seen = None if follow is None else follow.read_bytes()
    for a in range(0, len(rows), RATE):
        up.emit.clock = float(rows["time64_us"][min(a + RATE, len(rows)) - 1]) / 1e6
        up.feed(rows[a : a + RATE])
        if follow is not None and follow.read_bytes() != seen:
            seen = follow.read_bytes()
            up.reload(load_controller_config(follow))


def offset(config: Path, name: str) -> float:
    return float(load_controller_config(config).params[INDEX[name]])


def test_a_change_the_motion_cannot_attribute_is_said_at_once_and_never_written(tmp_path):
    truth, rows = scans(1, 420, TaskLoop(**AMBIGUOUS), [OffsetDrift("step", 4, 120.0, -0.6)])
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    before = config.read_bytes()
    up = upkeep(config)
    feed(up, rows)
    said = up.emit.of("offset_change")
    assert len(said) == 1, up.emit
    t, _, message, d = said[0]
    assert t - 120.0 <= 30.0, t
    names = [c["names"] for c in d["candidates"]]
    assert ["d04"] in names and ["d03"] in names and d["names"] == [], d
    assert "cannot tell which offset moved" in message and d["advice"] in message
    assert d["advice"].startswith(("tilt", "twist")), d["advice"]
    status = up.status()
    assert "LOOPS OPEN" in status and "d04" in status and "d03" in status, status
    metrics = {m.name: m for m in up.metrics()}
    assert metrics["loopcal_upkeep_change_unattributed"].samples[0].value == 1.0
    assert metrics["loopcal_upkeep_change"].samples[0].value == 1.0
    cands = {
        (s.labels["candidate"], s.labels["offset"])
        for s in metrics["loopcal_upkeep_candidate_shift_mm"].samples
    }
    assert {o for _, o in cands} >= {"d03", "d04"}
    assert config.read_bytes() == before  # nothing written to a sensor it cannot name
    assert not up.emit.of("recalibrated")


def test_the_motion_that_tells_them_apart_fixes_the_right_sensor(tmp_path):
    truth = truth_for(1)
    life = Phases([(0.0, TaskLoop(**AMBIGUOUS)), (300.0, HandMoves(1, params=truth))])
    truth, rows = scans(1, 420, life, [OffsetDrift("step", 4, 120.0, -0.6)])
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = upkeep(config)
    feed(up, rows, follow=config)
    written = up.emit.of("recalibrated")
    assert len(written) == 1, up.emit
    t, _, _, d = written[0]
    assert 300.0 < t <= 360.0, t  # within a minute of the hand
    assert list(d["values"]) == ["d04"]
    assert abs(offset(config, "d04") - (truth[INDEX["d04"]] - 0.6)) <= 0.05
    for name in ("d01", "d02", "d03"):
        assert offset(config, name) == truth[INDEX[name]]
    # a config loopcal never calibrated: the three held, 0.05 mm each, carried into d04
    assert len(up.emit.of("offsets_uncertain")) == 1, up.emit
    assert "OFFSETS UNCERTAIN" in up.status() and "loopcal session" in up.status()


def test_a_restart_takes_up_the_change_in_progress_and_says_it_at_once(tmp_path):
    truth, rows = scans(1, 420, TaskLoop(**AMBIGUOUS), [OffsetDrift("step", 4, 120.0, -0.6)])
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    state = state_path(tmp_path)
    first = upkeep(config, state=state)
    feed(first, rows[: 200 * RATE])
    assert len(first.emit.of("offset_change")) == 1
    first.close()  # the daemon stops (SIGKILL: the record is as of the last segment)
    again = upkeep(config, state=state)
    assert "LOOPS OPEN" in again.status() and "d04" in again.status()  # before any scan
    assert again.emit.kinds() == ["offset_change"]  # this run's recording says it too
    feed(again, rows[200 * RATE :])
    assert again.emit.kinds() == ["offset_change"], again.emit  # once
    assert "LOOPS OPEN" in again.status()
    again.close()
    # and loopcal upkeep status shows it from the record, the daemon running or not
    st = loopcal_main(
        "upkeep", "status", "--controller-config", config, "--recordings", tmp_path, "--json"
    )
    doc = json.loads(st.stdout)["record"]
    assert st.returncode == 1 and doc["current"] and not doc["baseline_ready"]
    assert doc["change"]["names"] == [] and doc["change"]["advice"]
    assert {c["names"][0] for c in doc["change"]["candidates"]} >= {"d03", "d04"}
    text = loopcal_main(
        "upkeep", "status", "--controller-config", config, "--recordings", tmp_path
    ).stdout
    assert "LOOPS OPEN since" in text and "not told apart yet" in text and "d04" in text


def test_a_swap_while_the_daemon_was_down_is_fixed_against_the_kept_baseline(tmp_path):
    truth, before = scans(2, 300, TaskLoop(2))
    _, after = scans(2, 240, TaskLoop(2), [OffsetDrift("step", 2, 0.0, 0.7)])
    after["stamp_ns"] += before["stamp_ns"][-1] - after["stamp_ns"][0] + 600 * 10**9
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    state = state_path(tmp_path)
    first = upkeep(config, state=state)
    feed(first, before)
    first.close()
    assert first.emit == [] and first.record.baseline.segments == 20
    again = upkeep(config, state=state)
    feed(again, after, follow=config)
    written = again.emit.of("recalibrated")
    assert len(written) == 1 and list(written[0][3]["values"]) == ["d02"], again.emit
    assert written[0][0] <= 60.0  # s of scans after the restart
    assert abs(offset(config, "d02") - (truth[INDEX["d02"]] + 0.7)) <= 0.05
    # without its record, at a config loopcal never calibrated, nothing is written
    (tmp_path / "other").mkdir()
    config2 = write_initial_config(tmp_path / "other" / "controller.toml", params=truth)
    fresh = upkeep(config2, state=state_path(tmp_path / "other"))
    feed(fresh, after)
    assert fresh.emit == [] and "never calibrated" in fresh.status()
    assert offset(config2, "d02") == truth[INDEX["d02"]]


def test_a_change_against_a_calibrated_config_is_fixed_with_no_baseline_kept(tmp_path):
    """The config's own calibration is the baseline: a sensor swapped before the daemon
    ever ran is a change since that calibration."""
    truth, rows = scans(3, 240, TaskLoop(3), [OffsetDrift("step", 1, 0.0, -0.5)])
    config = calibrated_config(tmp_path / "controller.toml", truth)
    up = upkeep(config)
    feed(up, rows, follow=config)
    written = up.emit.of("recalibrated")
    assert len(written) == 1 and list(written[0][3]["values"]) == ["d01"], up.emit
    assert written[0][0] <= 60.0
    assert abs(offset(config, "d01") - (truth[INDEX["d01"]] - 0.5)) <= 0.05
    # its std counts what the three held at 0.01 mm carry into it over this loop, said
    # and recorded: the fix is known no better than the offsets it was fitted against
    d = written[0][3]
    prov = load_controller_config(config).provenance
    assert d["std"]["d01"] > max(d["scans_std"]["d01"], 0.01), d
    assert "the scans' own" in written[0][2]
    assert prov["std"]["d01"] == d["std"]["d01"]
    assert [prov["std"][n] for n in ("d02", "d03", "d04")] == [0.01] * 3
    cov = np.array(prov["offset_cov"])
    assert np.isclose(np.sqrt(cov[0, 0]), d["std"]["d01"], rtol=1e-4)
    assert (cov[0, 1:] < 0).all()  # it took in what they are off by, the other way


@pytest.mark.parametrize(("std", "unsure"), [(0.01, False), (0.03, True)])
def test_a_fix_says_when_the_offsets_are_no_longer_known_to_the_threshold(tmp_path, std, unsure):
    """Over this task loop the four patterns correlate: a fix of d02 takes in what the
    three held are off by. Calibrated to 0.01 mm each, d02 is then known to about 0.02;
    to 0.03 mm, to about 0.05: three std beyond the threshold, which the daemon says
    (event, status line, metrics) once, and again at start, not at every reload."""
    truth, rows = scans(11, 240, TaskLoop(11), [OffsetDrift("step", 2, 60.0, 0.7)])
    config = calibrated_config(tmp_path / "c.toml", truth, std)
    state = state_path(tmp_path)
    up = upkeep(config, state=state)
    feed(up, rows, follow=config)
    (fix,) = up.emit.of("recalibrated")
    assert fix[3]["std"]["d02"] > 1.3 * max(std, fix[3]["scans_std"]["d02"]), fix[3]
    said = up.emit.of("offsets_uncertain")
    metrics = {m.name: m for m in up.metrics()}
    stds = {s.labels["offset"]: s.value for s in metrics["loopcal_upkeep_offset_std_mm"].samples}
    assert stds["d02"] == pytest.approx(fix[3]["std"]["d02"], rel=1e-3) and stds["d01"] == std
    assert metrics["loopcal_upkeep_offsets_uncertain"].samples[0].value == float(unsure)
    st = loopcal_main(
        "upkeep", "status", "--controller-config", config, "--recordings", tmp_path, "--json"
    )
    doc = json.loads(st.stdout)["offsets"]
    assert doc["std_mm"]["d02"] == pytest.approx(stds["d02"], abs=1e-4), doc
    assert doc["uncertain"] == (["d02"] if unsure else []), doc
    text = loopcal_main("upkeep", "status", "--controller-config", config).stdout
    assert ("OFFSETS UNCERTAIN (d02)" in text) == unsure and "offsets known to d01 +-" in text
    if not unsure:
        assert said == [] and "nothing changed" in up.status(), up.emit
        return
    assert len(said) == 1 and said[0][3]["std"] == {"d02": pytest.approx(stds["d02"], abs=1e-4)}
    assert said[0][0] == fix[0] and "loopcal session" in said[0][2]
    assert "OFFSETS UNCERTAIN: d02 +- 0.0" in up.status()
    up.reload(load_controller_config(config))  # SIGHUP: the same config, not said again
    assert len(up.emit.of("offsets_uncertain")) == 1
    up.close()
    again = upkeep(config, state=state)  # a restart: said at once
    assert again.emit.kinds() == ["offsets_uncertain"], again.emit


@pytest.mark.parametrize(("second", "mm"), [(1, -0.8), (3, -0.8)], ids=["another", "same"])
def test_two_swaps_minutes_apart_are_each_fixed_within_a_minute(tmp_path, second, mm):
    drifts = [OffsetDrift("step", 3, 60.0, 0.6), OffsetDrift("step", second, 240.0, mm)]
    truth, rows = scans(4, 420, TaskLoop(4), drifts)
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = upkeep(config)
    feed(up, rows, follow=config)
    written = up.emit.of("recalibrated")
    assert [list(d["values"]) for _, _, _, d in written] == [["d03"], [f"d0{second}"]], up.emit
    assert written[0][0] - 60.0 <= 60.0 and written[1][0] - 240.0 <= 60.0, written
    want = dict.fromkeys(("d01", "d02", "d03", "d04"), 0.0)
    want["d03"] += 0.6
    want[f"d0{second}"] += mm
    for name, shift in want.items():
        assert abs(offset(config, name) - (truth[INDEX[name]] + shift)) <= 0.05, name


@pytest.mark.slow
def test_a_swap_during_a_creep_is_fixed_and_nothing_else_moves(tmp_path):
    drifts = [OffsetDrift("creep", 1, 60.0, 0.02), OffsetDrift("step", 3, 300.0, -0.9)]
    truth, rows = scans(5, 480, TaskLoop(5), drifts)
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = upkeep(config)
    feed(up, rows, follow=config)
    fixed3 = [e for e in up.emit.of("recalibrated") if "d03" in e[3]["values"]]
    assert fixed3 and fixed3[0][0] - 300.0 <= 60.0, up.emit
    # within the tolerance, not the fit's 0.05 mm: d01 creeps by less than the threshold
    # when d03 is refitted alone, and their patterns correlate 0.9 over this loop
    assert abs(offset(config, "d03") - (truth[INDEX["d03"]] - 0.9)) <= 0.1
    for name in ("d02", "d04"):  # only what moved
        assert offset(config, name) == truth[INDEX[name]]
    creep_now = 0.02 * (480 - 60) / 60
    assert abs(offset(config, "d01") - (truth[INDEX["d01"]] + creep_now)) <= 0.2


@pytest.mark.skipif(not can_mount(), reason="mounting a small tmpfs needs root")
def test_a_full_disk_when_a_write_is_due_keeps_the_change_and_writes_once_it_can(tmp_path):
    truth, rows = scans(6, 300, TaskLoop(6), [OffsetDrift("step", 2, 60.0, 0.8)])
    with small_tmpfs(tmp_path / "small", "256k") as mnt:
        config = write_initial_config(mnt / "controller.toml", params=truth)
        before = config.read_bytes()
        filler = fill(mnt / "filler")  # the disk full to the last page
        up = upkeep(config)
        feed(up, rows[: 150 * RATE])
        refused = up.emit.of("recalibration_refused")
        assert len(refused) == 1 and "not written" in refused[0][2], up.emit
        assert "ENOSPC" in refused[0][2] or "space" in refused[0][2]
        assert config.read_bytes() == before and "identified but not written" in up.status()
        assert not [p for p in os.listdir(mnt) if p.endswith(".tmp")]
        filler.unlink()  # room again: written with the next segment
        feed(up, rows[150 * RATE :], follow=config)
        assert len(up.emit.of("recalibration_refused")) == 1  # said once
        assert len(up.emit.of("recalibrated")) == 1, up.emit
        assert abs(offset(config, "d02") - (truth[INDEX["d02"]] + 0.8)) <= 0.05


def test_a_swap_during_a_technicians_session_is_said_and_left_to_the_session(tmp_path):
    """While a session runs through the daemon (and a while after: its client writes
    then), the upkeep says what it sees but writes nothing: the technician's own
    calibration decides. Once it is over and nothing was written, the upkeep fixes it."""
    truth = truth_for(7)
    truth, rows = scans(7, 300, HandMoves(7, params=truth), [OffsetDrift("step", 1, 60.0, 0.5)])
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    before = config.read_bytes()
    up = upkeep(config)
    held = ["a technician's session runs (session 1 of tech)"]
    up.hold = lambda: held[0]
    feed(up, rows[: 150 * RATE])
    assert up.emit.kinds() == ["offset_change"], up.emit
    assert config.read_bytes() == before and "held while a technician's session" in up.status()
    held[0] = ""  # the session ended and wrote nothing
    feed(up, rows[150 * RATE :], follow=config)
    written = up.emit.of("recalibrated")
    assert len(written) == 1 and written[0][0] <= 150 + 20, up.emit
    assert abs(offset(config, "d01") - (truth[INDEX["d01"]] + 0.5)) <= 0.05


def test_a_swap_while_the_module_was_off_is_fixed_after_it_comes_back(tmp_path):
    """The module power-cycled (a new power-on: its counter and clock from 0) and a sensor
    was swapped meanwhile: the scans after it show the change against the baseline."""
    truth, before = scans(8, 240, TaskLoop(8))
    _, after = scans(8, 180, TaskLoop(8), [OffsetDrift("step", 3, 0.0, -0.7)])
    after["stamp_ns"] += before["stamp_ns"][-1] - after["stamp_ns"][0] + 20 * 10**9
    after["epoch"] = 1
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = upkeep(config)
    feed(up, np.concatenate([before, after]), follow=config)
    written = up.emit.of("recalibrated")
    assert len(written) == 1 and list(written[0][3]["values"]) == ["d03"], up.emit
    assert abs(offset(config, "d03") - (truth[INDEX["d03"]] - 0.7)) <= 0.05


def test_a_creep_is_said_before_the_config_is_out_of_tolerance(tmp_path):
    """A sensor creeping 0.04 mm/min: its shift's steady growth is said once it reaches
    half the threshold, before the config is 0.1 mm off, and fixed once the motion tells
    which sensor (over this loop sensors 1 and 2 correlate 0.97: at 0.35 mm). Each fix
    says with it that the creep goes on: the values just written will be off again."""
    truth, rows = scans(9, 900, TaskLoop(9), [OffsetDrift("creep", 2, 60.0, 0.04)])
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = upkeep(config)
    feed(up, rows, follow=config)
    warned = [e for e in up.emit.of("offset_change") if e[3].get("creeping")]
    assert warned, up.emit
    t, _, message, d = warned[0]
    assert 0.04 * (t - 60.0) / 60 < 0.1, t  # before it was out of tolerance
    fixed_at = [e[0] for e in up.emit.of("recalibrated")]
    for a, b in zip(warned, warned[1:], strict=False):  # again only with or after a fix
        assert any(a[0] < f <= b[0] for f in fixed_at), up.emit
    assert "creeps" in message and "d02" in [c["names"][0] for c in d["candidates"]]
    fixes = up.emit.of("recalibrated")
    assert fixes and all(list(e[3]["values"]) == ["d02"] for e in fixes), up.emit
    for f in fixed_at:  # the creep never stops here: every fix says it goes on
        on = [e for e in warned if e[0] == f]
        assert len(on) == 1 and "still creeps" in on[0][2], up.emit
        (cand,) = on[0][3]["candidates"]
        assert cand["names"] == ["d02"] and 0.02 <= cand["rate_mm_min"] <= 0.06, cand


def test_a_reload_in_the_middle_of_a_change_forgets_nothing(tmp_path):
    """SIGHUP (the recorder reloads the same controller config) while a change stands:
    the change goes on, said once, fixed once."""
    truth, rows = scans(10, 300, TaskLoop(10), [OffsetDrift("step", 4, 60.0, 0.9)])
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = upkeep(config, state=state_path(tmp_path))
    cut = 80 * RATE  # the change stands, not yet fixed
    feed(up, rows[:cut])
    before = up.record.change
    assert before is not None and not up.emit.of("recalibrated")
    up.reload(load_controller_config(config))
    assert up.record.change is before
    feed(up, rows[cut:], follow=config)
    assert len(up.emit.of("recalibrated")) == 1 and len(up.emit.of("offset_change")) <= 1
    assert abs(offset(config, "d04") - (truth[INDEX["d04"]] + 0.9)) <= 0.05

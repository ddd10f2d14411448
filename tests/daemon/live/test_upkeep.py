"""The daemon's upkeep, offline: the scans of a simulated robot at work (a task loop), a
sensor swapped or not, fed to :class:`Upkeep` as the recorder feeds it, a second at a time.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from loopcal.calibration.parameters import INDEX
from loopcal.daemon.config.controller import (
    ControllerConfigError,
    load_controller_config,
    write_initial_config,
)
from loopcal.daemon.live.upkeep import Upkeep
from loopcal.daemon.worker.proposal import apply_proposal, proposal_path, read_proposal
from loopcal.simulator.drift import OffsetDrift
from loopcal.simulator.offline import mechanism_scans
from loopcal.simulator.task import TaskLoop
from tests.support.fuzz import examples
from tests.support.recordings import write_directory
from tests.support.rows import rows_from
from tests.support.sessions import truth_for

RATE = 20


def robot_at_work(seed: int, seconds: float, drifts=()) -> tuple[np.ndarray, np.ndarray]:
    """(truth, scan rows) of a task loop."""
    truth = truth_for(seed)
    t_us, codes = mechanism_scans(TaskLoop(seed), truth, int(seconds * RATE), seed=seed,
                                  drifts=tuple(drifts))  # fmt: skip
    return truth, rows_from(t_us, codes)


class Events(list):
    def __call__(self, kind, level, message, **details):
        self.append((kind, message, details))

    def kinds(self) -> list[str]:
        return [k for k, _, _ in self]

    def acts(self) -> list[str]:
        """The kinds but the announcements of a change (at most one before its fix) and
        the words on how well the offsets are known (a config never calibrated: its
        offsets held at 0.05 mm carry into a fix)."""
        said = [k for k in self.kinds() if k == "offset_change"]
        assert len(said) <= 1, self
        return [k for k in self.kinds() if k not in ("offset_change", "offsets_uncertain")]


def run(upkeep: Upkeep, rows: np.ndarray, *, until: str | None = None) -> float | None:
    """Feed a second at a time; the seconds of scans fed when an event ``until`` came."""
    events = upkeep.emit
    for a in range(0, len(rows), RATE):
        upkeep.feed(rows[a:a + RATE])
        if until is not None and until in events.kinds():
            return (a + RATE) / RATE
    return None


def upkeep_for(path: Path, mode: str = "propose", **kw) -> Upkeep:
    settings = dict(target_mm=0.05, threshold_mm=0.1, min_interval_s=600.0)
    settings.update(kw)
    return Upkeep(load_controller_config(path), Events(), mode=mode, threaded=False, **settings)


@pytest.mark.parametrize(("seed", "sensor", "mm"), [(1, 3, 0.8), (2, 1, -0.3), (3, 4, 2.5)])
def test_a_swapped_sensor_is_proposed_once_within_two_minutes(tmp_path, seed, sensor, mm):
    truth, rows = robot_at_work(seed, 420, [OffsetDrift("step", sensor, 120.0, mm)])
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    before = config.read_bytes()
    up = upkeep_for(config)
    at = run(up, rows, until="recalibration_proposed")
    assert at is not None and at - 120.0 <= 120.0, up.emit
    run(up, rows[int(at * RATE):])  # the rest changes nothing
    assert up.emit.acts() == ["recalibration_proposed"], up.emit
    name = f"d0{sensor}"
    p = read_proposal(load_controller_config(config))
    assert p is not None and list(p.values) == [name]
    want = truth[INDEX[name]] + mm
    assert abs(p.values[name] - want) <= min(0.05, 3 * p.std[name]), (p.values, want, p.std)
    assert p.upkeep["change_since_ns"] <= int(rows["stamp_ns"][120 * RATE + 15 * RATE])
    assert config.read_bytes() == before  # propose writes nothing into the config
    assert "RECALIBRATION PROPOSED" in up.status()


@pytest.mark.slow
def test_shorter_segments_see_a_change_sooner(tmp_path):
    truth, rows = robot_at_work(1, 200, [OffsetDrift("step", 3, 120.0, 0.8)])
    at, fits = {}, {}
    for segment in (15.0, 5.0):
        (tmp_path / f"{segment:g}").mkdir()
        config = write_initial_config(tmp_path / f"{segment:g}" / "controller.toml", params=truth)
        up = upkeep_for(config, segment_s=segment)
        at[segment], fits[segment] = run(up, rows, until="recalibration_proposed"), up.state.fits
        p = read_proposal(load_controller_config(config))
        assert p is not None and abs(p.values["d03"] - (truth[INDEX["d03"]] + 0.8)) <= 0.05
    assert at[5.0] < at[15.0] and at[5.0] - 120.0 <= 25.0, at  # 21 s and 31 s after
    assert fits[5.0] > fits[15.0], fits


@pytest.mark.slow
def test_an_unchanged_robot_gets_no_proposal(tmp_path):
    truth, rows = robot_at_work(4, 1800)
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = upkeep_for(config)
    run(up, rows)
    assert up.emit == [] and not os.path.lexists(proposal_path(config))
    assert up.state.fits >= 1800 / 15 - 1  # every segment (the last needs a scan after it)


def test_two_sensors_swapped_at_once_are_both_found(tmp_path):
    drifts = [OffsetDrift("step", 2, 90.0, 0.6), OffsetDrift("step", 4, 90.0, -1.2)]
    truth, rows = robot_at_work(5, 360, drifts)
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = upkeep_for(config)
    assert run(up, rows, until="recalibration_proposed") is not None, up.emit
    p = read_proposal(load_controller_config(config))
    assert sorted(p.values) == ["d02", "d04"]
    for name, mm in (("d02", 0.6), ("d04", -1.2)):
        assert abs(p.values[name] - (truth[INDEX[name]] + mm)) <= 0.05


@pytest.mark.slow
def test_write_mode_rewrites_the_config_once_and_watches_the_new_values(tmp_path):
    truth, rows = robot_at_work(6, 600, [OffsetDrift("step", 3, 100.0, 1.0)])
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = upkeep_for(config, mode="write")
    at = run(up, rows, until="recalibrated")
    assert at is not None, up.emit
    new = load_controller_config(config)
    assert abs(new.params[INDEX["d03"]] - (truth[INDEX["d03"]] + 1.0)) <= 0.05
    assert new.provenance["upkeep"]["mode"] == "write"
    assert len(list(tmp_path.glob("controller.toml.*.prev"))) == 1  # the previous one kept
    up.reload(new)  # as the recorder does when it follows the file
    run(up, rows[int(at * RATE):])
    assert up.emit.acts() == ["recalibrated"], up.emit
    assert load_controller_config(config).sha256 == new.sha256


@pytest.mark.slow
def test_a_discarded_proposal_is_not_made_again(tmp_path):
    truth, rows = robot_at_work(7, 540, [OffsetDrift("step", 1, 60.0, 0.7)])
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = upkeep_for(config)
    at = run(up, rows, until="recalibration_proposed")
    assert at is not None
    os.replace(proposal_path(config), tmp_path / "aside")  # a person discards it
    run(up, rows[int(at * RATE):])
    assert up.emit.acts() == ["recalibration_proposed"]


@pytest.mark.slow
def test_a_proposal_damaged_or_edited_by_hand_is_refused_and_nothing_written(tmp_path):
    truth, rows = robot_at_work(8, 300, [OffsetDrift("step", 2, 60.0, 0.9)])
    recordings = write_directory(tmp_path / "rec", rows, rate=RATE)
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = upkeep_for(config)
    assert run(up, rows, until="recalibration_proposed") is not None
    path = proposal_path(config)
    good = path.read_text()
    before = config.read_bytes()
    loaded = load_controller_config(config)
    edited = good.replace(f"d02 = {read_proposal(loaded).values['d02']!r}", "d02 = 99.0")
    assert edited != good
    for text, why in ((edited, "edited|hand"), (good[: len(good) // 2], "damaged"),
                      ("[parameters]\nd01 = 1.0\n", "damaged|proposal")):  # fmt: skip
        path.write_text(text)
        with pytest.raises(ControllerConfigError, match=why):
            read_proposal(loaded)
        assert config.read_bytes() == before
    path.write_text(good)  # intact: applied, the gates checked again on its recordings
    written = apply_proposal(loaded, read_proposal(loaded), recordings, target_mm=0.05)
    assert written.backup.exists() and not os.path.lexists(path)
    assert load_controller_config(config).params[INDEX["d02"]] == pytest.approx(
        truth[INDEX["d02"]] + 0.9, abs=0.05)  # fmt: skip


def test_a_stale_proposal_is_set_aside_when_the_config_changes(tmp_path):
    truth, rows = robot_at_work(9, 300, [OffsetDrift("step", 4, 60.0, 0.7)])
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = upkeep_for(config)
    assert run(up, rows, until="recalibration_proposed") is not None
    config.write_text(config.read_text() + "\n# edited by hand\n")  # another version
    up.reload(load_controller_config(config))
    assert up.emit.kinds()[-1] == "recalibration_withdrawn"
    assert "another version" in up.emit[-1][1]
    assert not os.path.lexists(proposal_path(config))
    assert len(list(tmp_path.glob("controller.toml.proposed.*.discarded"))) == 1


def test_a_reload_takes_the_upkeep_settings_again(tmp_path):
    from dataclasses import replace

    from loopcal.daemon.recorder.settings import RecorderSettings

    truth, rows = robot_at_work(10, 300, [OffsetDrift("step", 2, 60.0, 0.8)])
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    settings = RecorderSettings(daq_url="modbus-tcp://127.0.0.1:1502", directory=tmp_path,
                                controller_config=config, upkeep_mode="off")  # fmt: skip
    current = [settings]
    loaded = load_controller_config(config)
    up = Upkeep(loaded, Events(), mode="off", target_mm=0.05, threshold_mm=0.1,
                min_interval_s=600, threaded=False, settings=lambda: current[0])  # fmt: skip
    run(up, rows)
    assert up.emit == [] and up.status() == "upkeep off"
    current[0] = replace(settings, upkeep_mode="propose")  # SIGHUP with the mode on
    up.reload(loaded)
    assert run(up, rows, until="recalibration_proposed") is not None


@pytest.fixture(scope="module")
def a_proposal(tmp_path_factory):
    """(controller config path, the proposal's text) made by the upkeep once."""
    tmp = tmp_path_factory.mktemp("proposal")
    truth, rows = robot_at_work(13, 240, [OffsetDrift("step", 3, 60.0, 0.6)])
    config = write_initial_config(tmp / "controller.toml", params=truth)
    assert run(upkeep_for(config), rows, until="recalibration_proposed") is not None
    return config, proposal_path(config).read_text()


@pytest.mark.slow
@given(st.data())
@settings(max_examples=examples(150), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
def test_any_mutation_of_a_proposal_is_refused_or_reads_as_written(a_proposal, data):
    """Fuzzed: a proposal cut, with bytes flipped, inserted or deleted anywhere reads back
    as the daemon wrote it or is refused with ControllerConfigError, never anything else."""
    config, text = a_proposal
    raw = bytearray(text.encode())
    for _ in range(data.draw(st.integers(1, 3))):
        i = data.draw(st.integers(0, len(raw) - 1))
        how = data.draw(st.sampled_from(["flip", "cut", "insert", "delete"]))
        if how == "flip":
            raw[i] ^= 1 << data.draw(st.integers(0, 7))
        elif how == "cut":
            del raw[i:]
        elif how == "insert":
            raw[i:i] = data.draw(st.binary(min_size=1, max_size=8))
        else:
            del raw[i:i + data.draw(st.integers(1, 40))]
        if not raw:
            break
    path = proposal_path(config)
    path.write_bytes(bytes(raw))
    loaded = load_controller_config(config)
    try:
        p = read_proposal(loaded)
    except ControllerConfigError:
        return
    finally:
        path.write_text(text)
    good = read_proposal(loaded)
    assert p is not None and p.values == good.values and p.upkeep["digest"] == good.upkeep["digest"]


def test_write_mode_never_overwrites_a_config_someone_else_wrote_meanwhile(tmp_path):
    truth, rows = robot_at_work(14, 300, [OffsetDrift("step", 1, 60.0, 0.8)])
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = upkeep_for(config, mode="write")  # it read the config
    theirs = config.read_text() + "\n# a person's calibration, written meanwhile\n"
    config.write_text(theirs)
    assert run(up, rows, until="recalibration_refused") is not None, up.emit
    refused = [m for k, m, _ in up.emit if k == "recalibration_refused"]
    assert len(refused) == 1 and "changed since" in refused[0] and "not written" in refused[0]
    assert config.read_text() == theirs and not list(tmp_path.glob("controller.toml.*"))

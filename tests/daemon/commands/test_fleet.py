"""``loopcal fleet`` on a local Dask cluster of two workers, over a few synthetic robots."""

from __future__ import annotations

import csv
import json

import pytest

from loopcal.daemon.config.controller import write_initial_config
from loopcal.simulator.drift import OffsetDrift
from loopcal.simulator.scenarios import HandMoves
from tests.support.processes import loopcal_main
from tests.support.rows import T0
from tests.support.sessions import PAUSE_S, truth_for, write_session

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]
DAY_NS = 86_400 * 10**9


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """Three robots, two days each of six minutes in three-minute files; robot-c's sensor 2
    offset steps by +0.6 mm on its second day; robot-b's config sits beside its files."""
    root = tmp_path_factory.mktemp("fleet")
    for k, robot in enumerate(["robot-a", "robot-b", "robot-c"]):
        truth = truth_for(20 + k)
        d = root / robot
        files = d if robot == "robot-b" else d / "recordings"
        for day in range(2):
            drifts = (OffsetDrift("step", 2, 200.0, 0.6),) if robot == "robot-c" and day else ()
            write_session(files, HandMoves(20 + k + 10 * day, params=truth, pause_s=PAUSE_S),
                          truth, 360, seed=20 + k + 10 * day, hours_per_file=3 / 60,
                          drifts=drifts, t0=T0 + day * DAY_NS)  # fmt: skip
        write_initial_config(d / "controller.toml", params=truth)
    (root / "not-a-robot").mkdir()  # no recordings: ignored
    return root


def table(path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_fleet_info_is_one_row_per_robot_day(fleet, tmp_path):
    out = tmp_path / "info.csv"
    proc = loopcal_main("fleet", "info", fleet, "--table", out, "--workers", "2")
    assert proc.returncode == 0, proc.stderr
    rows = table(out)
    assert [(r["robot"], r["day"]) for r in rows] == [
        (robot, day) for robot in ("robot-a", "robot-b", "robot-c")
        for day in ("2026-11-18", "2026-11-19")
    ]  # fmt: skip
    assert all(int(r["scans"]) == 7200 and int(r["files"]) == 2 for r in rows)
    assert all(int(r["missed"]) == 0 and int(r["poses"]) > 100 for r in rows)
    assert "6 robot-days of 3 robot(s) on a local cluster of 2 worker(s)" in proc.stderr
    assert "6/6 robot-days done" in proc.stderr
    as_json = loopcal_main("fleet", "info", fleet, "--json", "--workers", "2")
    assert as_json.returncode == 0, as_json.stderr
    doc = json.loads(as_json.stdout)
    assert doc["columns"] == list(rows[0])
    assert [{k: "" if v is None else str(v) for k, v in r.items()} for r in doc["rows"]] == rows


def test_fleet_check_finds_the_robot_and_day_whose_sensor_moved(fleet, tmp_path):
    out = tmp_path / "check.csv"
    proc = loopcal_main("fleet", "check", fleet, "--table", out, "--workers", "2")
    assert proc.returncode == 1, proc.stderr  # a change was found
    rows = {(r["robot"], r["day"]): r for r in table(out)}
    moved = rows["robot-c", "2026-11-19"]
    assert moved["loops_close"] == "False" and moved["sensors"] == "2"
    assert abs(float(moved["shifts_mm"]) - 0.6) < 0.15
    others = [r for key, r in rows.items() if key != ("robot-c", "2026-11-19")]
    assert len(others) == 5 and all(r["loops_close"] == "True" for r in others)
    # the daemon's upkeep would propose sensor 2's offset, on that robot-day alone
    name, shift = moved["proposals"].split()
    assert name == "d02" and abs(float(shift) - 0.6) < 0.1, moved["proposals"]
    assert all(r["proposals"] == "-" for r in others)
    columns = list(moved)
    assert columns.index("proposals") == columns.index("first_change_utc") + 1


def test_fleet_check_json_has_the_proposals_column(fleet):
    proc = loopcal_main("fleet", "check", fleet, "--json", "--workers", "2")
    assert proc.returncode == 1, proc.stderr
    doc = json.loads(proc.stdout)
    assert "proposals" in doc["columns"]
    column = {(r["robot"], r["day"]): r["proposals"] for r in doc["rows"]}
    assert column.pop(("robot-c", "2026-11-19")).startswith("d02 +0.")
    assert set(column.values()) == {"-"}


def test_fleet_bad_input(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    proc = loopcal_main("fleet", "info", empty)
    assert proc.returncode == 2 and "no robot directories with recordings" in proc.stderr
    proc = loopcal_main("fleet", "info", tmp_path / "missing")
    assert proc.returncode == 2 and "not a directory" in proc.stderr
    proc = loopcal_main("fleet", "check", empty, "--workers", "0")
    assert proc.returncode == 2 and "--workers 0" in proc.stderr
    proc = loopcal_main("fleet", "check", empty, "--upkeep-threshold-mm", "20")
    assert proc.returncode == 2 and "--upkeep-threshold-mm 20" in proc.stderr

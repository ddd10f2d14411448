"""The alert rules docs/daemon.md gives, as Prometheus itself reads them: `promtool check
rules` and `promtool test rules` (tests/project/prometheus/loopcal-alerts.test.yml: for every alert,
a case that fires and one that does not), and against real scrapes of `loopcal record
--metrics`: a recorder at the reference geometry fires LoopcalNeverCalibrated, one at a
config loopcal calibrated a moment ago fires nothing about calibration, one whose module
never answers fires LoopcalNoScans."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import textwrap
import time
import urllib.request
from datetime import UTC, datetime
from pathlib import Path

import pytest

from loopcal.daemon.config.controller import load_controller_config, write_initial_config
from loopcal.daemon.worker.writeback import write_back
from tests.support import ROOT
from tests.support.emulator import hand_emulator
from tests.support.processes import free_port, record
from tests.support.sessions import truth_for

pytestmark = [
    pytest.mark.skipif(
        shutil.which("promtool") is None,
        reason="promtool is not installed (Debian: apt-get install prometheus)",
    ),
    pytest.mark.timeout(120),
]

UNIT_TESTS = Path(__file__).resolve().parent / "prometheus" / "loopcal-alerts.test.yml"
RULES_NAME = "loopcal-alerts.yml"  # what the unit tests' rule_files name


def documented_rules() -> str:
    """The rule file docs/daemon.md shows: the indented block after "Example alert rules"."""
    lines = (ROOT / "docs" / "daemon.md").read_text(encoding="utf-8").splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith("Example alert rules"))
    while not lines[i].startswith("    "):
        i += 1
    j = i
    while j < len(lines) and (lines[j].startswith("    ") or not lines[j].strip()):
        j += 1
    return textwrap.dedent("\n".join(lines[i:j])).strip() + "\n"


def promtool(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["promtool", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=60)  # fmt: skip


def rules_in(tmp: Path) -> Path:
    path = tmp / RULES_NAME
    path.write_text(documented_rules(), encoding="utf-8")
    return path


def test_the_documented_rules_are_valid_and_each_alert_is_tested(tmp_path):
    rules = documented_rules()
    alerts = re.findall(r"^\s*- alert: (\w+)$", rules, re.M)
    assert "LoopcalNeverCalibrated" in alerts and len(alerts) == len(set(alerts)) >= 5
    tests = UNIT_TESTS.read_text(encoding="utf-8")
    cases: dict[str, set[str]] = {}
    for name, empty in re.findall(r"alertname: (\w+)\n\s+exp_alerts:( \[\])?", tests):
        cases.setdefault(name, set()).add("silent" if empty else "fires")
    assert cases == {a: {"fires", "silent"} for a in alerts}
    rules_in(tmp_path)
    shutil.copy(UNIT_TESTS, tmp_path)
    check = promtool("check", "rules", RULES_NAME, cwd=tmp_path)
    assert check.returncode == 0 and f"SUCCESS: {len(alerts)} rules found" in check.stdout, (
        check.stdout + check.stderr
    )
    run = promtool("test", "rules", UNIT_TESTS.name, cwd=tmp_path)
    assert run.returncode == 0 and "SUCCESS" in run.stdout, run.stdout + run.stderr


#: alert -> (its expression in docs/daemon.md, an old one that did not fire when it should)
FIXED_RULES = {
    # the age is NaN (now absent) when never calibrated
    "LoopcalNeverCalibrated": (
        "loopcal_controller_config_calibrated == 0",
        "loopcal_controller_config_calibration_age_seconds > 365 * 86400",
    ),
    # no scan age before the first scan: a module that answers but never scans went unseen
    "LoopcalNoScans": (
        "loopcal_last_scan_age_seconds > 10 or loopcal_daq_connected == 0 or "
        "(time() - loopcal_recorder_start_time_seconds > 10 unless loopcal_last_scan_age_seconds)",
        "loopcal_last_scan_age_seconds > 10 or loopcal_daq_connected == 0",
    ),
}


def with_expr(rules: str, alert: str, expr: str | None = None) -> tuple[str, str]:
    """The rule file with ``alert``'s expression replaced by ``expr`` (None: kept), and the
    expression it had (a folded block's lines joined by spaces)."""
    lines = rules.splitlines()
    i = lines.index(next(line for line in lines if line.strip() == f"- alert: {alert}"))
    i += next(k for k, line in enumerate(lines[i:]) if line.strip().startswith("expr:"))
    indent = len(lines[i]) - len(lines[i].lstrip())
    j = i + 1
    while len(lines[j]) - len(lines[j].lstrip()) > indent:
        j += 1
    had = " ".join(line.strip() for line in lines[i:j]).removeprefix("expr:").strip()
    had = had.removeprefix(">-").strip()
    if expr is not None:
        lines[i:j] = [" " * indent + f"expr: {expr}"]
    return "\n".join(lines) + "\n", had


@pytest.mark.parametrize("alert", FIXED_RULES)
def test_the_unit_tests_fail_for_the_old_rule(tmp_path, alert):
    """An old rule that never fired where it should: the unit tests say so, so they can
    tell a rule that works from one that does not."""
    fixed, old = FIXED_RULES[alert]
    text, had = with_expr(documented_rules(), alert, old)
    assert had == fixed
    (tmp_path / RULES_NAME).write_text(text, encoding="utf-8")
    shutil.copy(UNIT_TESTS, tmp_path)
    run = promtool("test", "rules", UNIT_TESTS.name, cwd=tmp_path)
    assert run.returncode != 0 and alert in run.stdout + run.stderr


def scrape_text(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
        return r.read().decode()


def live_scrape(out: Path, *extra: str) -> str:
    """/metrics of a real `loopcal record --metrics`, a second after it started recording."""
    port = free_port()
    with hand_emulator(speed=4.0) as emu:
        rec = record(emu.url, out, "--metrics", f"127.0.0.1:{port}", *extra)
        try:
            rec.wait_for("recording to", timeout=30)
            time.sleep(1.0)
            text = scrape_text(port)
            assert rec.stop()[0] == 0, rec.text
        finally:
            rec.kill()
    return text


def samples(text: str, name: str) -> list[float]:
    return [float(v) for v in re.findall(rf"^{name} (\S+)$", text, re.M)]


#: the calibration metrics of a scrape, as the calibration alerts read them
CALIBRATION = ("loopcal_controller_config_calibrated",
               "loopcal_controller_config_calibration_age_seconds")  # fmt: skip


def held(text: str, *names: str) -> dict[str, str]:
    """The scraped samples of ``names`` as promtool input series held for 10 min (an age
    growing with time)."""
    return {name: f"{v!r}+{60 if name.endswith('age_seconds') else 0}x10"
            for name in names for v in samples(text, name)}  # fmt: skip


def alerts_on(
    values: dict[str, str], tmp: Path, expected: dict[str, list[dict]]
) -> subprocess.CompletedProcess:
    """`promtool test rules` with input series of one recorder, ``{name: values}`` a minute
    apart, and the alerts expected after 5 min."""
    series = [{"series": f'{name}{{instance="live", job="loopcal"}}', "values": v}
              for name, v in values.items()]  # fmt: skip
    test = {
        "rule_files": [RULES_NAME],
        "evaluation_interval": "1m",
        "tests": [{
            "interval": "1m",
            "input_series": series,
            "alert_rule_test": [{"eval_time": "5m", "alertname": a, "exp_alerts": exp}
                                for a, exp in expected.items()],
        }],
    }  # fmt: skip
    rules_in(tmp)
    (tmp / "live.test.yml").write_text(json.dumps(test, indent=1), encoding="utf-8")  # JSON is YAML
    return promtool("test", "rules", "live.test.yml", cwd=tmp)


@pytest.mark.slow
def test_a_recorder_never_calibrated_fires_the_alert(tmp_path):
    text = live_scrape(tmp_path / "rec")
    assert samples(text, "loopcal_controller_config_calibrated") == [0.0]
    assert samples(text, "loopcal_controller_config_calibration_age_seconds") == []  # absent
    lint = subprocess.run(["promtool", "check", "metrics"], input=text, capture_output=True,
                          text=True, timeout=60)  # fmt: skip
    assert lint.returncode == 0, lint.stdout + lint.stderr
    run = alerts_on(held(text, *CALIBRATION), tmp_path, {
        "LoopcalNeverCalibrated": [{
            "exp_labels": {"severity": "info", "instance": "live", "job": "loopcal"},
            "exp_annotations": {"summary": "live: loopcal never calibrated the controller config"},
        }],
        "LoopcalCalibrationOverAYearOld": [],
    })  # fmt: skip
    assert run.returncode == 0, run.stdout + run.stderr


@pytest.mark.slow
def test_a_recorder_calibrated_a_moment_ago_fires_nothing_about_it(tmp_path):
    path = write_initial_config(tmp_path / "controller.toml")
    written_utc = datetime.now(UTC).isoformat(timespec="seconds")
    write_back(load_controller_config(path), truth_for(2),
               {"written_utc": written_utc, "method": "ml"})  # fmt: skip
    assert load_controller_config(path).provenance["written_utc"] is not None
    t0 = time.time()
    text = live_scrape(tmp_path / "rec", "--controller-config", str(path))
    assert samples(text, "loopcal_controller_config_calibrated") == [1.0]
    [age] = samples(text, "loopcal_controller_config_calibration_age_seconds")
    since = datetime.fromisoformat(written_utc).timestamp()
    assert t0 - since - 1 <= age <= time.time() - since + 1
    run = alerts_on(
        held(text, *CALIBRATION),
        tmp_path,
        {"LoopcalNeverCalibrated": [], "LoopcalCalibrationOverAYearOld": []},
    )
    assert run.returncode == 0, run.stdout + run.stderr


@pytest.mark.slow
def test_a_recorder_whose_module_never_answers_fires_no_scans(tmp_path):
    """A module unplugged at boot (nothing listens at its port): the recorder's metrics say
    it is not connected, when the recorder started, and no scan age (no scan ever came);
    promtool, fed those, fires LoopcalNoScans for it."""
    port = free_port()
    t0 = time.time()
    rec = record(f"modbus-tcp://127.0.0.1:{free_port()}?unit=1", tmp_path / "rec",
                 "--metrics", f"127.0.0.1:{port}")  # fmt: skip
    try:
        rec.wait_for("disconnect: DAQDisconnected", timeout=30)
        text = scrape_text(port)
        scraped = time.time()
        rec.stop()  # "nothing was recorded": its exit status says so
    finally:
        rec.kill()
    assert samples(text, "loopcal_daq_connected") == [0.0]
    [started] = samples(text, "loopcal_recorder_start_time_seconds")
    assert t0 <= started <= scraped
    assert samples(text, "loopcal_last_scan_age_seconds") == []  # absent, not NaN
    lint = subprocess.run(["promtool", "check", "metrics"], input=text, capture_output=True,
                          text=True, timeout=60)  # fmt: skip
    assert lint.returncode == 0, lint.stdout + lint.stderr
    values = held(text, "loopcal_daq_connected")
    # promtool's clock starts at 0 when the scrape was taken: the recorder started before
    values["loopcal_recorder_start_time_seconds"] = f"{started - scraped!r}x10"
    run = alerts_on(values, tmp_path, {
        "LoopcalNoScans": [{
            "exp_labels": {"severity": "critical", "instance": "live", "job": "loopcal"},
            "exp_annotations": {"summary": "live: no scan for 10 s"},
        }],
    })  # fmt: skip
    assert run.returncode == 0, run.stdout + run.stderr

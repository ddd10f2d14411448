"""Every bad input gets a clear error naming the option and the value, exit status 2, no
traceback, and nothing is started, recorded or written. Each case was a traceback once."""

from __future__ import annotations

import json

import pytest

from loopcal.daemon import recording as rec
from tests.support.processes import fresh_config, loopcal_main, taken_port
from tests.support.recordings import write_recording
from tests.support.rows import T0, make_rows

pytestmark = pytest.mark.timeout(120)


def refused(proc, *words: str) -> None:
    text = proc.stdout + proc.stderr
    assert proc.returncode == 2, text
    assert "Traceback" not in text, text
    for w in words:
        assert w in text, (w, text)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("url", "words"),
    [
        ("modbus-tcp://127.0.0.1:5020?unit=300", ("unit=300", "1..247")),
        ("modbus-tcp://127.0.0.1:5020?unit=abc", ("unit='abc'", "not an integer")),
        ("modbus-tcp://127.0.0.1:5020?fifo=maybe", ("fifo='maybe'",)),
        ("modbus-tcp://:5020", ("no host",)),
        ("modbus-tcp://127.0.0.1:0", ("port 0",)),
        ("modbus-rtu:///dev/null?baud=-5", ("baud=-5",)),
        ("ascii:///dev/null?addr=zz", ("addr='zz'",)),
    ],
)
def test_bad_driver_urls_are_refused_before_anything_starts(tmp_path, url, words):
    out = tmp_path / "rec"
    refused(loopcal_main("record", "--daq", url, "--out", out, "--duration", "1"), "--daq", *words)
    assert not out.exists() or not list(out.iterdir())
    cfg = tmp_path / "daemon.toml"
    cfg.write_text(f'[daq]\nurl = "{url}"\n[recording]\ndirectory = "{out}"\n')
    refused(loopcal_main("daemon", "--config", cfg), "[daq].url", *words)


@pytest.mark.slow
def test_an_absurd_controller_config_is_refused_naming_the_key(tmp_path):
    config = fresh_config(tmp_path / "controller.toml")
    config.write_text(config.read_text().replace("A1x = 68.7", "A1x = 1e300"))
    refused(
        loopcal_main(
            "record",
            "--daq",
            "modbus-tcp://127.0.0.1:1",
            "--out",
            tmp_path / "r",
            "--controller-config",
            config,
            "--duration",
            "1",
        ),  # fmt: skip
        "A1x",
        "1e+300",
    )
    recording = tmp_path / rec.recording_name(T0)
    write_recording(recording, make_rows(200))
    proc = loopcal_main("calibrate", recording, "--controller-config", config)
    refused(proc, "A1x", "plausible")
    assert "Eigenvalues" not in proc.stderr


@pytest.mark.slow
def test_calibrate_options(tmp_path):
    config = fresh_config(tmp_path / "controller.toml")
    recording = tmp_path / rec.recording_name(T0)
    write_recording(recording, make_rows(200))
    refused(loopcal_main("calibrate", recording, "--controller-config", config, "--last",
                    "99999999999d"), "--last", "3650 days")  # fmt: skip
    refused(loopcal_main("calibrate", recording, "--controller-config", config, "--ties",
                    "A4x=-A1x"), "--ties goes with --free")  # fmt: skip
    window = ("--since", "2030-01-01T00:00:00Z", "--until", "2029-01-01T00:00:00Z")
    proc = loopcal_main("calibrate", recording, "--controller-config", config, *window)
    refused(proc, "empty time window", "2030-01-01T00:00:00.000Z")
    proc = loopcal_main("calibrate", recording, "--controller-config", config,
                   "--since", "2031-01-01T00:00:00Z")  # fmt: skip
    refused(proc, "no scans", "from 2031-01-01T00:00:00.000Z")
    assert " ns" not in proc.stderr
    # a time as `info` prints it is a time every time option takes (one spelling)
    info = json.loads(loopcal_main("info", recording, "--json").stdout)
    for when in (info["start_utc"], info["start_utc"].replace("T", " ")[:-1] + " UTC"):
        proc = loopcal_main("calibrate", recording, "--controller-config", config,
                            "--since", when, "--until", info["end_utc"], "--json")
        assert proc.returncode != 2 and "not a time" not in proc.stderr, proc.stderr
        assert json.loads(proc.stdout)["poses"]["scans"] == 200 - 1  # until: not included


@pytest.mark.slow
def test_report_path_is_checked_before_the_config_is_written(tmp_path):
    config = fresh_config(tmp_path / "controller.toml")
    before = config.read_bytes()
    blocker = tmp_path / "report.html"
    blocker.write_text("not a directory")
    recording = tmp_path / rec.recording_name(T0)
    write_recording(recording, make_rows(200))
    proc = loopcal_main("calibrate", recording, "--controller-config", config, "--write",
                   "--report", blocker)  # fmt: skip
    refused(proc, "--report", "not a directory")
    assert config.read_bytes() == before and not list(tmp_path.glob("*.prev"))


@pytest.mark.slow
def test_replay_and_simulate_options(tmp_path):
    recording = tmp_path / rec.recording_name(T0)
    write_recording(recording, make_rows(100))
    for cmd in (["replay", recording], ["simulate", "--duration", "1"]):
        refused(loopcal_main(*cmd, "--port", "70000"), "--port", "70000", "0..65535")
        refused(loopcal_main(*cmd, "--host", "256.1.1.1"), "--host", "256.1.1.1")
        with taken_port() as port:
            refused(loopcal_main(*cmd, "--port", port), f"127.0.0.1:{port}", "in use")
        refused(loopcal_main(*cmd, "--max-read-registers", "0"), "--max-read-registers", "1..125")
        refused(loopcal_main(*cmd, "--slow-answers", "0.1"), "--slow-answers needs --latency")
    refused(loopcal_main("simulate", "--truth-out", "/no/dir/t.jsonl", "--duration", "1"),
            "--truth-out /no/dir/t.jsonl")  # fmt: skip
    eight = tmp_path / "eight.mcap"
    eight.write_bytes(b"\x01\x02\x03\x04\x05\x06\x07\x08")
    refused(loopcal_main("replay", eight), str(eight), "not an MCAP file")
    eight.write_bytes(b"\x89MCAP0\r\n")
    refused(loopcal_main("replay", eight), str(eight), "no scans")


@pytest.mark.slow
def test_demo_out_must_be_a_directory(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    refused(loopcal_main("demo", "--out", blocker), "--out", "not a directory")
    refused(loopcal_main("demo", "--out", blocker / "sub"), "--out", "Not a directory")

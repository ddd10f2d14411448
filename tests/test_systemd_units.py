"""The systemd units, checked with systemd's own tools (installed by .ci/run if missing)."""

from __future__ import annotations

import configparser
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNITS = Path(__file__).parent.parent / "systemd"
SERVICES = ("loopcal.service", "loopcal-calibrate.service")
INSTALLED_BINARY = "/opt/loopcal/bin/loopcal"


def tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.fail(f"{name} is missing: .ci/run installs Debian's systemd package for it")
    return path


def unit(name: str) -> configparser.ConfigParser:
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.optionxform = str  # keys are case-sensitive
    cp.read_string((UNITS / name).read_text())
    return cp


def local_copy(tmp_path: Path, name: str) -> Path:
    """The unit with ExecStart pointing at this environment's loopcal (verify checks it)."""
    loopcal = shutil.which("loopcal") or str(Path(sys.executable).parent / "loopcal")
    assert Path(loopcal).exists()
    copy = tmp_path / name
    copy.write_text((UNITS / name).read_text().replace(INSTALLED_BINARY, loopcal))
    return copy


@pytest.mark.parametrize("name", SERVICES)
def test_systemd_analyze_verify_is_clean(tmp_path, name):
    assert INSTALLED_BINARY in (UNITS / name).read_text()
    proc = subprocess.run([tool("systemd-analyze"), "verify", str(local_copy(tmp_path, name))],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    problems = [line for line in (proc.stdout + proc.stderr).splitlines() if name in line]
    assert not problems, problems


def test_verify_catches_a_broken_unit(tmp_path):
    broken = local_copy(tmp_path, "loopcal.service")
    broken.write_text(broken.read_text().replace("Restart=on-failure", "Restart=sometimes"))
    proc = subprocess.run([tool("systemd-analyze"), "verify", str(broken)],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    # systemd only warns (exit 0): the clean check above looks at what it prints
    problems = [line for line in proc.stderr.splitlines() if "loopcal.service" in line]
    assert problems and "sometimes" in problems[0]


@pytest.mark.parametrize("name", SERVICES)
def test_exposure_is_at_most_two(name):
    proc = subprocess.run(
        [tool("systemd-analyze"), "security", "--offline=yes", str(UNITS / name)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    m = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", proc.stdout)
    assert m, proc.stdout + proc.stderr
    assert float(m.group(1)) <= 2.0, proc.stdout


def test_the_daemon_unit_is_what_the_daemon_needs():
    s = unit("loopcal.service")["Service"]
    assert s["Type"] == "notify" and s["NotifyAccess"] == "main"
    assert int(s["WatchdogSec"]) >= 10 and s["Restart"] == "on-failure"
    assert s["User"] == "loopcal" and "dialout" in s["SupplementaryGroups"]
    assert s["ProtectSystem"] == "strict" and s["NoNewPrivileges"] == "yes"
    assert "PrivateDevices" not in s and "PrivateUsers" not in s  # both would hide ttys
    assert "daemon --config /etc/loopcal/daemon.toml" in s["ExecStart"]
    assert "-HUP" in s["ExecReload"] and s["StateDirectory"] == "loopcal"
    assert unit("loopcal.service")["Install"]["WantedBy"] == "multi-user.target"
    c = unit("loopcal-calibrate.service")["Service"]
    assert c["Type"] == "oneshot" and "/etc/loopcal" in c["ReadWritePaths"]
    assert "WatchdogSec" not in c and "Restart" not in c


def test_sysusers_and_tmpfiles_make_the_user_and_directories(tmp_path):
    sysusers, tmpfiles = shutil.which("systemd-sysusers"), shutil.which("systemd-tmpfiles")
    if sysusers is None or tmpfiles is None:
        pytest.skip("systemd-sysusers / systemd-tmpfiles not installed")
    root = tmp_path / "root"
    for sub in ("sysusers.d", "tmpfiles.d"):
        (root / "etc" / sub).mkdir(parents=True)
        shutil.copy(UNITS / sub / "loopcal.conf", root / "etc" / sub)
    users = subprocess.run([sysusers, f"--root={root}"], capture_output=True, text=True)
    assert users.returncode == 0 and "loopcal.conf:" not in users.stderr, users.stderr
    passwd = (root / "etc" / "passwd").read_text()
    group = (root / "etc" / "group").read_text()
    assert re.search(r"^loopcal:x:\d+:\d+:.*:/var/lib/loopcal:", passwd, re.M)
    assert re.search(r"^dialout:x:\d+:.*loopcal", group, re.M)
    dirs = subprocess.run([tmpfiles, f"--root={root}", "--create"], capture_output=True, text=True)
    assert dirs.returncode == 0 and "loopcal.conf:" not in dirs.stderr, dirs.stderr
    uid = int(re.search(r"^loopcal:x:(\d+):", passwd, re.M).group(1))
    for d in ("var/lib/loopcal", "var/lib/loopcal/recordings"):
        st = (root / d).stat()
        assert (st.st_mode & 0o777, st.st_uid) == (0o750, uid), d
    assert (root / "etc" / "loopcal").stat().st_mode & 0o777 == 0o755

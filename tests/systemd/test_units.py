"""The systemd units, checked with systemd's own tools (.ci/run installs them if missing)."""

from __future__ import annotations

import configparser
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support import ROOT

UNITS = ROOT / "systemd"
SERVICES = ("loopcal.service", "loopcal-calibrate.service")
INSTALLED_BINARY = "/opt/loopcal/bin/loopcal"
# Hardening both services share (the worker adds PrivateNetwork=, PrivateDevices=, ...).
SHARED = (
    "User", "Group", "NoNewPrivileges", "ProtectSystem", "ProtectHome", "PrivateTmp",
    "ProtectKernelTunables", "ProtectKernelModules", "ProtectKernelLogs",
    "ProtectControlGroups", "ProtectClock", "ProtectHostname", "ProtectProc", "ProcSubset",
    "RestrictNamespaces", "RestrictRealtime", "RestrictSUIDSGID", "LockPersonality",
    "MemoryDenyWriteExecute", "SystemCallArchitectures", "CapabilityBoundingSet",
    "IPAddressDeny", "StateDirectory", "StateDirectoryMode", "ConfigurationDirectory",
    "ConfigurationDirectoryMode",
)  # fmt: skip


def tool(name: str) -> str:
    """The path of a systemd tool; a missing one fails the test (CI must have it)."""
    path = shutil.which(name)
    if path is None:
        pytest.fail(f"{name} is missing: .ci/run installs Debian's systemd package for it")
    return path


def unit(name: str) -> configparser.ConfigParser:
    """The unit file parsed; for a key given several times, its last value."""
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.optionxform = str  # keys are case-sensitive
    cp.read_string((UNITS / name).read_text())
    return cp


def values(name: str, section: str, key: str) -> list[str]:
    """Every value of ``key`` in ``section``, in order (DeviceAllow= etc. repeat)."""
    out, current = [], None
    for line in (UNITS / name).read_text().splitlines():
        if m := re.fullmatch(r"\[(\w+)\]", line.strip()):
            current = m.group(1)
        elif current == section and line.startswith(f"{key}="):
            out.append(line.split("=", 1)[1])
    return out


def local_copy(tmp_path: Path, name: str, text: str | None = None) -> Path:
    """The unit (or ``text``) with ExecStart pointing at this environment's loopcal:
    verify checks that the binary exists."""
    loopcal = shutil.which("loopcal") or str(Path(sys.executable).parent / "loopcal")
    assert Path(loopcal).exists(), loopcal
    copy = tmp_path / name
    text = (UNITS / name).read_text() if text is None else text
    copy.write_text(text.replace(INSTALLED_BINARY, loopcal))
    return copy


def verify_problems(path: Path) -> list[str]:
    """What ``systemd-analyze verify`` says about the unit at ``path`` (it also reads the
    host's units the unit depends on: only lines naming this unit count), and its status."""
    proc = subprocess.run([tool("systemd-analyze"), "verify", str(path)],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    lines = [ln for ln in (proc.stdout + proc.stderr).splitlines() if path.name in ln]
    return lines + ([f"exit status {proc.returncode}"] if proc.returncode else [])


@pytest.mark.parametrize("name", SERVICES)
def test_systemd_analyze_verify_is_clean(tmp_path, name):
    assert INSTALLED_BINARY in (UNITS / name).read_text()
    assert verify_problems(local_copy(tmp_path, name)) == []


@pytest.mark.parametrize(
    ("old", "new", "said"),
    [
        ("WatchdogSec=30", "WatchdogSecs=30", "WatchdogSecs"),
        ("Restart=on-failure", "Restart=sometimes", "sometimes"),
        ("[Service]", "[Servce]", "Servce"),
        ("ProtectSystem=strict", "ProtectSystem=very", "very"),
    ],
)
def test_verify_catches_a_broken_unit(tmp_path, old, new, said):
    text = (UNITS / "loopcal.service").read_text()
    assert old in text
    problems = verify_problems(local_copy(tmp_path, "loopcal.service", text.replace(old, new)))
    assert any(said in p for p in problems), problems


@pytest.mark.parametrize("name", SERVICES)
def test_exposure_is_at_most_two(name):
    # --offline=yes reads the unit file given by path (a bare name is looked up as installed)
    proc = subprocess.run(
        [tool("systemd-analyze"), "security", "--offline=yes", str(UNITS / name)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    m = re.search(rf"Overall exposure level for {re.escape(name)}: (\d+\.\d+)", proc.stdout)
    assert m, proc.stdout + proc.stderr
    assert float(m.group(1)) <= 2.0, proc.stdout


def test_the_daemon_unit_is_what_the_daemon_needs():
    u = unit("loopcal.service")
    s = u["Service"]
    assert s["Type"] == "notify" and s["NotifyAccess"] == "main"
    assert int(s["WatchdogSec"]) >= 10 and s["Restart"] == "on-failure"
    assert s["RestartPreventExitStatus"] == "2"  # a config error: no restart loop
    assert "StartLimitIntervalSec" in u["Unit"] and "StartLimitBurst" in u["Unit"]
    assert s["User"] == "loopcal" and "dialout" in s["SupplementaryGroups"]
    assert s["ProtectSystem"] == "strict" and s["NoNewPrivileges"] == "yes"
    assert "PrivateDevices" not in s and "PrivateUsers" not in s  # both would hide ttys
    assert s["DevicePolicy"] == "closed"
    assert values("loopcal.service", "Service", "DeviceAllow") == [
        "char-ttyS rw", "char-ttyUSB rw", "char-ttyACM rw"
    ]  # fmt: skip
    assert set(s["RestrictAddressFamilies"].split()) == {"AF_INET", "AF_INET6", "AF_UNIX"}
    assert s["IPAddressDeny"] == "any" and "192.168.0.0/16" in s["IPAddressAllow"]
    assert s["ExecStart"] == f"{INSTALLED_BINARY} daemon --config /etc/loopcal/daemon.toml"
    assert "-HUP" in s["ExecReload"] and s["StateDirectory"] == "loopcal"
    # the upkeep's proposals and writes: the controller config's directory, nothing else
    assert s["ReadWritePaths"].split() == ["/etc/loopcal/controller"]
    assert "OPENBLAS_NUM_THREADS=1" in s["Environment"]  # else TasksMax= kills numpy
    assert u["Install"]["WantedBy"] == "multi-user.target"


def test_the_worker_unit_is_a_hardened_one_shot_that_may_write_the_config():
    d, c = unit("loopcal.service")["Service"], unit("loopcal-calibrate.service")["Service"]
    # the controller config's own directory, and not the daemon's config beside it
    assert c["Type"] == "oneshot" and c["ReadWritePaths"].split() == ["/etc/loopcal/controller"]
    assert c["ExecStart"].startswith(f"{INSTALLED_BINARY} calibrate --config ")
    assert "--write" in c["ExecStart"].split()
    assert "WatchdogSec" not in c and "Restart" not in c
    assert {k: c.get(k) for k in SHARED} == {k: d.get(k) for k in SHARED}
    assert c["PrivateNetwork"] == "yes" and c["RestrictAddressFamilies"] == "AF_UNIX"
    # the new controller config gets the old one's mode: the umask must not narrow it
    assert int(c["UMask"], 8) & 0o044 == 0


def test_tmpfiles_agrees_with_the_units_directory_modes():
    lines = [ln.split() for ln in (UNITS / "tmpfiles.d" / "loopcal.conf").read_text().splitlines()]
    dirs = {f[1]: (f[2], f[3], f[4]) for f in lines if f and f[0] == "d"}
    s = unit("loopcal.service")["Service"]
    # a mismatch makes systemd warn (ConfigurationDirectory=) or chmod (StateDirectory=)
    assert dirs["/var/lib/loopcal"] == (s["StateDirectoryMode"], "loopcal", "loopcal")
    assert dirs["/etc/loopcal"] == (s["ConfigurationDirectoryMode"], "root", "root")
    assert not int(dirs["/etc/loopcal"][0], 8) & 0o022  # daemon.toml: root's alone
    assert dirs["/etc/loopcal/controller"] == ("0775", "root", "loopcal")  # the worker's
    # the control socket and the lock files: the group's, where every loopcal process looks
    assert dirs["/run/loopcal"] == (s["RuntimeDirectoryMode"], "loopcal", "loopcal")
    assert s["RuntimeDirectory"] == "loopcal" and s["RuntimeDirectoryPreserve"] == "yes"
    assert int(s["RuntimeDirectoryMode"], 8) & 0o070 == 0o070


def test_sysusers_and_tmpfiles_make_the_user_and_directories(tmp_path):
    sysusers, tmpfiles = shutil.which("systemd-sysusers"), shutil.which("systemd-tmpfiles")
    if sysusers is None or tmpfiles is None:
        pytest.skip("systemd-sysusers / systemd-tmpfiles not installed")
    # a scratch root: both tools read their config from it and write only inside it
    root = tmp_path / "root"
    for sub in ("sysusers.d", "tmpfiles.d"):
        (root / "etc" / sub).mkdir(parents=True)
        shutil.copy(UNITS / sub / "loopcal.conf", root / "etc" / sub)
    dry = subprocess.run([sysusers, "--dry-run", f"--root={root}"],
                         capture_output=True, text=True, timeout=60)  # fmt: skip
    assert dry.returncode == 0 and "loopcal.conf:" not in dry.stderr, dry.stderr
    assert "Creating user 'loopcal'" in dry.stderr and not (root / "etc" / "passwd").exists()
    users = subprocess.run([sysusers, f"--root={root}"],
                           capture_output=True, text=True, timeout=60)  # fmt: skip
    assert users.returncode == 0 and "loopcal.conf:" not in users.stderr, users.stderr
    passwd = (root / "etc" / "passwd").read_text()
    group = (root / "etc" / "group").read_text()
    assert re.search(r"^loopcal:x:\d+:\d+:.*:/var/lib/loopcal:", passwd, re.M), passwd
    assert re.search(r"^dialout:x:\d+:(.*,)?loopcal(,|$)", group, re.M), group
    dirs = subprocess.run([tmpfiles, f"--root={root}", "--create"],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert dirs.returncode == 0 and "loopcal.conf:" not in dirs.stderr, dirs.stderr
    uid = int(re.search(r"^loopcal:x:(\d+):", passwd, re.M).group(1))
    gid = int(re.search(r"^loopcal:x:(\d+):", group, re.M).group(1))
    for d in ("var/lib/loopcal", "var/lib/loopcal/recordings"):
        st = (root / d).stat()
        assert (st.st_mode & 0o777, st.st_uid, st.st_gid) == (0o750, uid, gid), d
    st = (root / "etc" / "loopcal").stat()
    assert (st.st_mode & 0o777, st.st_uid, st.st_gid) == (0o755, 0, 0)
    st = (root / "etc" / "loopcal" / "controller").stat()
    assert (st.st_mode & 0o777, st.st_uid, st.st_gid) == (0o775, 0, gid)
    st = (root / "run" / "loopcal").stat()
    assert (st.st_mode & 0o7777, st.st_uid, st.st_gid) == (0o2770, uid, gid)


def test_the_daemon_unit_lets_it_serve_metrics_on_loopback():
    """[metrics] listen = "127.0.0.1:9464": the hardening must allow a loopback listener."""
    s = unit("loopcal.service")["Service"]
    assert {"AF_INET", "AF_INET6"} <= set(s["RestrictAddressFamilies"].split())
    assert "localhost" in s["IPAddressAllow"].split()
    assert not any(k.startswith("SocketBind") for k in s)  # binding a port is not restricted
    assert "@network-io" not in values("loopcal.service", "Service", "SystemCallFilter")[-1]

"""``loopcal upkeep status|apply|discard`` on a proposal the daemon's upkeep made from a
robot at work whose sensor 2 was swapped (offline scans, recorded as the daemon records)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from loopcal.calibration.parameters import INDEX
from loopcal.daemon.config.controller import load_controller_config, write_initial_config
from loopcal.daemon.live.upkeep import Upkeep
from loopcal.daemon.worker.proposal import proposal_path
from loopcal.simulator.drift import OffsetDrift
from loopcal.simulator.offline import mechanism_scans
from loopcal.simulator.task import TaskLoop
from tests.support.processes import loopcal_main
from tests.support.recordings import write_directory
from tests.support.rows import rows_from
from tests.support.sessions import truth_for

RATE, SWAP_MM = 20, 0.9


@pytest.fixture
def proposed(tmp_path):
    """(truth, controller config, recordings, daemon config) with a proposal pending."""
    truth = truth_for(11)
    t_us, codes = mechanism_scans(TaskLoop(11), truth, 300 * RATE, seed=11,
                                  drifts=(OffsetDrift("step", 2, 60.0, SWAP_MM),))  # fmt: skip
    rows = rows_from(t_us, codes)
    recordings = write_directory(tmp_path / "rec", rows, rate=RATE)
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    kinds = []
    up = Upkeep(load_controller_config(config), lambda kind, *a, **k: kinds.append(kind),
                mode="propose", target_mm=0.05, threshold_mm=0.1, min_interval_s=600,
                threaded=False)  # fmt: skip
    for a in range(0, len(rows), RATE):
        up.feed(rows[a:a + RATE])
    words = ("offset_change", "offsets_uncertain")  # never calibrated: 0.05 mm held
    assert [k for k in kinds if k not in words] == ["recalibration_proposed"]
    daemon = tmp_path / "daemon.toml"
    daemon.write_text(f'[daq]\nurl = "modbus-tcp://127.0.0.1:1502"\n[recording]\n'
                      f'directory = "{recordings}"\n'
                      f'[controller]\nconfig = "{config}"\n')  # fmt: skip
    return truth, config, recordings, daemon


@pytest.mark.slow
def test_status_shows_the_proposal_and_apply_writes_it(proposed):
    truth, config, recordings, daemon = proposed
    before = config.read_bytes()
    st = loopcal_main("upkeep", "status", "--config", daemon)
    assert st.returncode == 0, st.stderr
    assert "d02" in st.stdout and "loopcal calibrate" in st.stdout and "gates:" in st.stdout
    doc = json.loads(loopcal_main("upkeep", "status", "--config", daemon, "--json").stdout)
    assert doc["pending"] and list(doc["values"]) == ["d02"]
    assert config.read_bytes() == before  # status writes nothing
    ap = loopcal_main("upkeep", "apply", "--config", daemon)
    assert ap.returncode == 0, ap.stderr
    new = load_controller_config(config)
    assert abs(new.params[INDEX["d02"]] - (truth[INDEX["d02"]] + SWAP_MM)) <= 0.05
    others = [n for n in INDEX if n != "d02"]
    assert all(new.params[INDEX[n]] == truth[INDEX[n]] for n in others)
    assert new.provenance["upkeep"]["applied_utc"]
    assert not os.path.lexists(proposal_path(config))
    assert list(config.parent.glob("controller.toml.*.prev"))  # the previous version kept
    again = loopcal_main("upkeep", "status", "--config", daemon)
    assert again.returncode == 1 and "no recalibration proposed" in again.stdout


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["edit a value", "truncate", "edit the provenance",
                                    "config changed since"])  # fmt: skip
def test_a_damaged_or_edited_proposal_is_refused_and_nothing_written(proposed, damage):
    _, config, _, daemon = proposed
    path = proposal_path(config)
    text = path.read_text()
    if damage == "edit a value":
        lines = [ln if not ln.startswith("d02 =") else "d02 = 97.5" for ln in text.splitlines()]
        path.write_text("\n".join(lines) + "\n")
    elif damage == "truncate":
        path.write_bytes(path.read_bytes()[: len(text) // 3])
    elif damage == "edit the provenance":
        path.write_text(text.replace("change_since_utc = ", "change_since_utc = \"x\"\nz = ", 1))
    else:
        config.write_text(config.read_text() + "\n# a comment added by hand\n")
    before = config.read_bytes()
    ap = loopcal_main("upkeep", "apply", "--config", daemon)
    assert ap.returncode == 2 and "nothing applied" in ap.stderr, ap.stderr
    assert "Traceback" not in ap.stderr
    assert config.read_bytes() == before
    assert not list(config.parent.glob("controller.toml.*.prev"))


@pytest.mark.slow
def test_discard_sets_it_aside(proposed):
    _, config, _, daemon = proposed
    d = loopcal_main("upkeep", "discard", "--config", daemon, "--json")
    assert d.returncode == 0, d.stderr
    doc = json.loads(d.stdout)
    assert doc["discarded"] and os.path.exists(doc["aside"])
    assert not os.path.lexists(proposal_path(config))
    assert loopcal_main("upkeep", "status", "--config", daemon).returncode == 1


@pytest.mark.slow
def test_bad_options_are_named():
    p = loopcal_main("upkeep", "status")
    assert p.returncode == 2 and "--config" in p.stderr and "Traceback" not in p.stderr
    np.testing.assert_equal(loopcal_main("upkeep", "frobnicate").returncode, 2)

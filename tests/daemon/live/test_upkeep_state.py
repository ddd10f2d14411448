"""The upkeep's kept record (upkeep-state.json): read back exactly as written, any damage
refused with a ValueError naming it (fuzzed), a newer format refused naming its version,
and a damaged file set aside at start with an event while the upkeep starts over."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from loopcal.daemon.config.controller import load_controller_config, write_initial_config
from loopcal.daemon.live.changes import Normal
from loopcal.daemon.live.upkeep import Upkeep
from loopcal.daemon.live.upkeep_state import (
    Change,
    UpkeepRecord,
    load_record,
    reference_digest,
    save_record,
    state_path,
)
from tests.support.fuzz import examples
from tests.support.sessions import truth_for


def a_record() -> UpkeepRecord:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(4, 4))
    n = Normal(A @ A.T, rng.normal(size=4), 1234, 7)
    change = Change(
        1_795_000_100_000_000_000,
        n,
        1_795_000_110_000_000_000,
        n + n,
        np.array([0.0, 0.0, 0.0, -0.6]),
        ["d04"],
        [{"names": ["d04"], "shift_mm": [-0.6], "std_mm": [0.01], "statistic": 9.0}],
        "",
        True,
        False,
        1,
    )
    rec = UpkeepRecord(
        reference_digest(truth_for(1)),
        "ab" * 32,
        1_795_000_000_000_000_000,
        n,
        change,
        {"d03": [1_795_000_050_000_000_000, 0.8, False]},
    )
    rec.note_trend(1_795_000_090_000_000_000, np.array([0.1, 0.0, -0.1, 0.02]), np.full(4, 0.01))
    rec.last_action = {"kind": "recalibrated", "ns": 1, "values": {"d03": 99.1}}
    return rec


def test_a_record_reads_back_as_written(tmp_path):
    rec = a_record()
    path = state_path(tmp_path)
    save_record(path, rec)
    back = load_record(path)
    assert back.as_json() == rec.as_json()
    assert not [p for p in os.listdir(tmp_path) if p != path.name]  # no temporary left
    assert load_record(tmp_path / "none.json") is None


def test_a_newer_format_is_refused_naming_its_version(tmp_path):
    path = state_path(tmp_path)
    doc = a_record().as_json()
    doc["version"] = 7
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="version 7.*upgrade loopcal"):
        load_record(path)


@given(st.data())
@settings(
    max_examples=examples(300),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
def test_any_damage_is_refused_or_reads_as_a_record(tmp_path, data):
    """Fuzzed: bytes flipped, cut, inserted or deleted; numbers and types swapped in the
    JSON: a record comes back (valid) or ValueError, never anything else."""
    raw = bytearray(json.dumps(a_record().as_json()).encode())
    for _ in range(data.draw(st.integers(1, 3))):
        i = data.draw(st.integers(0, len(raw) - 1))
        how = data.draw(st.sampled_from(["flip", "cut", "insert", "delete", "number"]))
        if how == "flip":
            raw[i] ^= 1 << data.draw(st.integers(0, 7))
        elif how == "cut":
            del raw[i:]
        elif how == "insert":
            raw[i:i] = data.draw(
                st.sampled_from(
                    [
                        b"-",
                        b"1e999",
                        b"NaN",
                        b"[]",
                        b"{}",
                        b'"x"',
                        b"null",
                        b"true",
                        b"9" * 30,
                        b"\xff",
                    ]
                )
            )
        elif how == "delete":
            del raw[i : i + data.draw(st.integers(1, 40))]
        else:
            raw[i:i] = str(data.draw(st.floats(allow_nan=True))).encode()
        if not raw:
            break
    path = tmp_path / "upkeep-state.json"
    path.write_bytes(bytes(raw))
    try:
        rec = load_record(path)
    except ValueError as exc:
        assert str(exc)
        return
    assert rec is not None and np.isfinite(rec.baseline.N).all()
    assert rec.baseline.scans >= 0 and len(rec.reference) == 64


def test_a_damaged_record_is_set_aside_said_and_the_upkeep_starts_over(tmp_path):
    config = write_initial_config(tmp_path / "controller.toml", params=truth_for(1))
    path = state_path(tmp_path)
    path.write_text('{"version": 1, "reference": "')
    events = []
    up = Upkeep(
        load_controller_config(config),
        lambda k, lv, m, **d: events.append((k, m, d)),
        mode="write",
        target_mm=0.05,
        threshold_mm=0.1,
        min_interval_s=600,
        threaded=False,
        state=path,
    )
    assert [k for k, _, _ in events] == ["upkeep_reset"], events
    assert "not JSON" in events[0][1] and "set aside" in events[0][1]
    aside = events[0][2]["aside"]
    assert os.path.exists(aside) and not path.exists()  # nothing lost
    assert up.record.baseline.segments == 0 and up.record.change is None

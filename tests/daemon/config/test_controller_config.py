"""The controller config: init-config, reading it back, and every way it can be wrong."""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import subprocess
import sys
import tomllib

import numpy as np
import pytest
import tomlkit
from hypothesis import example, given, settings
from hypothesis import strategies as st

from loopcal.calibration.errors import ParameterError
from loopcal.calibration.parameters import NAMES, NOMINAL, PRESETS, UNITS
from loopcal.daemon.config.controller import (
    ControllerConfig,
    ControllerConfigError,
    load_controller_config,
    nominal_config,
    render_initial_config,
    write_initial_config,
)
from tests.support.fuzz import examples

GOOD = render_initial_config()


def init_config(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "daemon.commands.init_config", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def bits(a: np.ndarray) -> bytes:
    return np.asarray(a, dtype="<f8").tobytes()


# ------------------------------------------------------------------------- init-config


def test_init_config_writes_the_reference_geometry_with_comments(tmp_path):
    path = tmp_path / "controller.toml"
    proc = init_config(str(path))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == [
        f"wrote {path}: the 20 parameters at the reference geometry "
        "(edit the gains S1..S4 to your bench values)"
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["controller.toml"]  # no temp left
    cfg = load_controller_config(path)
    assert bits(cfg.params) == bits(NOMINAL)
    assert cfg.free == "paper7" and cfg.ties == () and cfg.provenance is None
    assert cfg.text == path.read_text(encoding="utf-8") == GOOD
    assert cfg.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    assert cfg.model() == PRESETS["paper7"]
    lines = GOOD.splitlines()
    assert lines[0].startswith("# loopcal controller config")
    for name in NAMES:
        (i,) = [k for k, line in enumerate(lines) if line.split(" = ")[0] == name]
        comment = lines[i - 1]
        assert comment.startswith("# ") and comment.endswith(f", {UNITS[name]}"), name


@pytest.mark.slow
def test_init_config_refuses_to_overwrite_unless_forced(tmp_path):
    path = tmp_path / "controller.toml"
    mine = b"# my own \xff\x00 config\n"
    path.write_bytes(mine)
    path.chmod(0o640)
    proc = init_config(str(path))
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.startswith(f"loopcal init-config: error: {path}: already exists")
    assert "--force" in proc.stderr
    assert path.read_bytes() == mine
    forced = init_config(str(path), "--force")
    assert forced.returncode == 0, forced.stderr
    assert bits(load_controller_config(path).params) == bits(NOMINAL)
    assert path.stat().st_mode & 0o777 == 0o640  # the replaced file's permissions are kept
    assert sorted(p.name for p in tmp_path.iterdir()) == ["controller.toml"]


@pytest.mark.slow
def test_init_config_creates_no_directories(tmp_path):
    target = tmp_path / "no" / "such" / "controller.toml"
    proc = init_config(str(target))
    assert proc.returncode == 2
    assert f"directory {target.parent} does not exist" in proc.stderr
    assert not (tmp_path / "no").exists()
    (tmp_path / "file").write_text("x")
    proc = init_config(str(tmp_path / "file" / "controller.toml"))
    assert proc.returncode == 2 and "is not a directory" in proc.stderr


def test_any_valid_vector_is_written_and_read_back_bit_for_bit(tmp_path):
    rng = np.random.default_rng(7)
    extremes = [0.0, -0.0, 5e-324, -1e-300, 1e17, 0.1 + 0.2, np.nextafter(97.4, 98.0), 1 / 3]
    for k in range(40):
        p = NOMINAL * (1 + 1e-3 * rng.standard_normal(NOMINAL.shape))
        if k % 2:  # the text round-trips any float (these describe no mechanism: not loaded)
            p[:9] = rng.choice(extremes, 9)
            doc = tomllib.loads(render_initial_config(p))["parameters"]
            assert bits(np.array([doc[n] for n in NAMES])) == bits(p)
            continue
        path = write_initial_config(tmp_path / "c.toml", force=True, params=p)
        assert bits(load_controller_config(path).params) == bits(p)
    with pytest.raises(ParameterError, match="positive"):
        render_initial_config(np.where(np.arange(20) == 12, -1.0, NOMINAL))


# -------------------------------------------------------------------------- round trip


def test_editing_one_value_keeps_every_comment(tmp_path):
    doc = tomlkit.parse(GOOD)
    doc["parameters"]["d03"] = 99.125
    edited = tomlkit.dumps(doc)
    before, after = GOOD.splitlines(), edited.splitlines()
    changed = [(a, b) for a, b in zip(before, after, strict=True) if a != b]
    assert changed == [("d03 = 97.4", "d03 = 99.125")]
    path = tmp_path / "c.toml"
    path.write_text(edited)
    params = load_controller_config(path).params
    expected = NOMINAL.copy()
    expected[NAMES.index("d03")] = 99.125
    assert bits(params) == bits(expected)


# ------------------------------------------------------------------------------ errors


def _set(name: str, value: str) -> str:
    line = f"{name} = {float(NOMINAL[NAMES.index(name)])!r}\n"
    assert line in GOOD
    return GOOD.replace(line, f"{name} = {value}\n" if value else "")


def _cal(free: str | None = None, ties: str | None = None) -> str:
    """GOOD with ``[calibration]``'s values replaced by TOML text."""
    text = GOOD if free is None else GOOD.replace('free = "paper7"', f"free = {free}")
    return text if ties is None else text.replace("ties = []", f"ties = {ties}")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", r"no \[parameters\] table"),
        ("[parameters\n", r"not valid TOML: .*\(at line 1, column 12\)"),
        (_set("d03", "97.4\nd03 = 98.0"),
         r"not valid TOML: Cannot overwrite .*\(at line \d+, column"),
        (_set("d03", '"abc"'), r"\[parameters\]\.d03 = 'abc' is not a number"),
        (_set("d03", "true"), r"\[parameters\]\.d03 = True is not a number"),
        (_set("d03", "[97.4]"), r"\[parameters\]\.d03 = \[97\.4\] is not a number"),
        (_set("d03", "1979-05-27"), r"\[parameters\]\.d03 = .*1979.* is not a number"),
        (_set("d03", "nan"), r"\[parameters\]\.d03 = nan is not finite"),
        (_set("S1", "-inf"), r"\[parameters\]\.S1 = -inf is not finite"),
        (_set("d03", "1" + "0" * 400), r"\[parameters\]\.d03 = 10+ is not finite"),
        (_set("d03", ""), r"\[parameters\] lacks d03$"),
        (_set("d02", "").replace("A1x = 68.7\n", "").replace("S4 = 3.75\n", ""),
         r"\[parameters\] lacks A1x, S4, d02$"),
        (_set("d03", "97.4\nd3 = 1.0"),
         r"\[parameters\]\.d3: unknown parameter \(did you mean d03\?\)"),
        (_set("d03", "97.4\nzz = 1.0\nS11 = 1.0"),
         r"\[parameters\]\.zz: unknown parameter; \[parameters\]\.S11: unknown parameter \(did"),
        (_set("S2", "-3.75"), r"\[parameters\]: plate sizes and gains must be positive: S2$"),
        (_set("k3", "300"), r"\[parameters\]: k1=100\.0, k2=100\.0, k3=300\.0 do not form"),
        (GOOD + "\n[robot]\nname = 'x'\n", r"unknown table or key 'robot'"),
        ("name = 'x'\n" + GOOD, r"unknown table or key 'name'"),
        ("provenance = 'x'\n" + GOOD, r"provenance = 'x' must be a table \[provenance\]"),
        ("parameters = 1\n", r"parameters = 1 must be a table \[parameters\]"),
        (_cal('"Q7"'), r"\[calibration\]\.free = 'Q7': unknown parameter 'Q7'"),
        (_cal('"d01,d01"'), r"\[calibration\]\.free = 'd01,d01': parameters listed twice"),
        (_cal("7"), r"\[calibration\]\.free = 7: give a preset"),
        (_cal('""'), r"\[calibration\]\.free = '': give"),
        (_cal(ties="'A4x=-A1x'"), r"\[calibration\]\.ties = 'A4x=-A1x': give a list of strings"),
        (_cal(ties="[1]"), r"\[calibration\]\.ties = \[1\]: give a list"),
        (_cal(ties='["A4x=-A1x"]'),
         r"\[calibration\]\.ties = \['A4x=-A1x'\]: the preset 'paper7' brings its own ties"),
        (_cal('"d02"', '["A4x=-A1x"]'),
         r"\[calibration\]\.ties = \['A4x=-A1x'\]: A4x is tied to A1x, which is not free"),
        (_cal('"A1x"', '["A4x"]'),
         r"\[calibration\]\.ties = \['A4x'\]: tie 'A4x' must read follower=leader"),
        (_cal('"offsets"', '["A4x=-d01"]'),
         r"\[calibration\]\.ties = \['A4x=-d01'\]: the preset 'offsets' brings its own ties"),
        (_cal('"d03,A1x"', '["A1x=d03"]'),
         r"\[calibration\]\.ties = \['A1x=d03'\]: A1x is free and cannot also be tied"),
        (_cal(ties="[]\nfreedom = 1"),
         r"\[calibration\]\.freedom: unknown key \(it has free, ties\)"),
    ],
)  # fmt: skip
def test_every_problem_names_the_file_and_the_key(tmp_path, text, message):
    path = tmp_path / "controller.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ControllerConfigError, match=message) as err:
        load_controller_config(path)
    assert str(err.value).startswith(f"{path}: ")


def test_missing_unreadable_and_not_utf8(tmp_path):
    missing = tmp_path / "missing.toml"
    with pytest.raises(ControllerConfigError, match="no such file") as err:
        load_controller_config(missing)
    assert str(err.value).startswith(f"{missing}: ") and "loopcal init-config" in str(err.value)
    with pytest.raises(ControllerConfigError, match="cannot read the controller config"):
        load_controller_config(tmp_path)  # a directory
    bad = tmp_path / "latin1.toml"
    bad.write_bytes(("# caf\xe9\n" + GOOD).encode("latin-1"))
    with pytest.raises(ControllerConfigError, match=r"latin1\.toml: not UTF-8 text \(byte 5\)"):
        load_controller_config(bad)
    bom = tmp_path / "bom.toml"
    bom.write_bytes(b"\xef\xbb\xbf" + GOOD.encode())
    with pytest.raises(ControllerConfigError, match="byte order mark"):
        load_controller_config(bom)


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads files whatever their mode")
def test_unreadable(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(GOOD)
    path.chmod(0)
    with pytest.raises(ControllerConfigError, match="cannot read.*Permission denied"):
        load_controller_config(path)


def test_integers_are_floats_and_calibration_is_optional(tmp_path):
    path = tmp_path / "c.toml"
    text = _set("d03", "97").split("[calibration]")[0]
    path.write_text(text)
    cfg = load_controller_config(path)
    assert cfg.params[NAMES.index("d03")] == 97.0 and cfg.params.dtype == np.float64
    assert cfg.free is None and cfg.ties == () and cfg.model() == PRESETS["paper7"]


# ------------------------------------------------------------------ metadata and model


def test_metadata_and_model(tmp_path):
    path = tmp_path / "c.toml"
    doc = tomlkit.parse(GOOD)
    doc["calibration"]["free"] = "d03"
    when = dt.datetime(2026, 11, 22, 10, 0, tzinfo=dt.UTC)
    doc["provenance"] = {"written": when, "poses": 50, "std": {"d03": 0.01}}
    path.write_text(tomlkit.dumps(doc))
    cfg = load_controller_config(path)
    assert cfg.provenance == {"written": when, "poses": 50, "std": {"d03": 0.01}}
    meta = cfg.as_metadata()
    assert set(meta) == {"path", "sha256", *NAMES, "free", "ties", "provenance"}
    assert all(isinstance(k, str) and isinstance(v, str) for k, v in meta.items())
    assert bits([float(meta[n]) for n in NAMES]) == bits(cfg.params)
    assert meta["path"] == str(path) and meta["sha256"] == cfg.sha256
    assert meta["free"] == "d03" and meta["ties"] == ""
    compact = '{"written":"2026-11-22 10:00:00+00:00","poses":50,"std":{"d03":0.01}}'
    assert meta["provenance"] == compact
    assert json.loads(meta["provenance"])["poses"] == 50
    assert list(cfg.model().free) == ["d03"] and cfg.model().tied == ()


def test_custom_free_set_with_ties(tmp_path):
    path = tmp_path / "c.toml"
    doc = tomlkit.parse(GOOD)
    doc["calibration"]["free"] = "d01,d02,A1x"
    doc["calibration"]["ties"] = ["A4x=-A1x"]
    path.write_text(tomlkit.dumps(doc))
    cfg = load_controller_config(path)
    assert cfg.ties == ("A4x=-A1x",) and cfg.as_metadata()["ties"] == "A4x=-A1x"
    model = cfg.model()
    assert model.free == ("d01", "d02", "A1x") and model.tied == ("A4x",)
    assert model.tie_matrix[NAMES.index("A4x"), 2] == -1.0


def test_nominal_config():
    cfg = nominal_config()
    assert cfg.path is None and cfg.text == "" and cfg.sha256 == "" and cfg.free is None
    assert bits(cfg.params) == bits(NOMINAL)
    assert list(cfg.model().free) == ["d01", "d02", "d03", "d04", "A1x", "A2x", "A2y"]
    meta = cfg.as_metadata()
    assert meta["path"] == "" and meta["free"] == "" and "provenance" not in meta
    assert float(meta["k3"]) == NOMINAL[NAMES.index("k3")]


def test_a_config_is_immutable_and_compares_by_its_text(tmp_path):
    path = write_initial_config(tmp_path / "c.toml")
    a, b = load_controller_config(path), load_controller_config(path)
    assert isinstance(a, ControllerConfig) and a == b and hash(a) == hash(b)
    assert a != nominal_config()
    with pytest.raises(ValueError, match="read-only"):
        a.params[0] = 1.0
    with pytest.raises(AttributeError):
        a.free = "all"  # type: ignore[misc]


def test_write_initial_config_errors(tmp_path):
    path = write_initial_config(tmp_path / "c.toml")
    with pytest.raises(ControllerConfigError, match=r"c\.toml: already exists; use --force"):
        write_initial_config(path)
    with pytest.raises(ControllerConfigError, match="does not exist"):
        write_initial_config(tmp_path / "missing" / "c.toml")
    (tmp_path / "dir.toml").mkdir()
    with pytest.raises(ControllerConfigError, match="cannot write"):
        write_initial_config(tmp_path / "dir.toml", force=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.toml", "dir.toml"]


def test_a_recordings_controller_record_gives_back_its_parameters_bit_for_bit():
    from loopcal.daemon.config.controller import nominal_config, params_from_metadata
    from tests.support.sessions import truth_for

    for params in (NOMINAL, truth_for(3)):
        record = replace_params(nominal_config(), params).as_metadata()
        got, why = params_from_metadata(record)
        assert why == "" and got.tobytes() == np.asarray(params, dtype=float).tobytes()
        del record[NAMES[5]]
        assert params_from_metadata(record) == (None, f"its controller_config record lacks "
                                                      f"{NAMES[5]}")  # fmt: skip


def replace_params(config, params):
    from dataclasses import replace

    return replace(config, params=tuple(float(x) for x in params))


@pytest.mark.slow
@settings(max_examples=examples(300), deadline=None)
@given(record=st.dictionaries(st.sampled_from([*NAMES, "path", "junk"]),
                              st.one_of(st.text(max_size=12), st.sampled_from(
                                  ["nan", "inf", "-inf", "1e308", "0", "97.4", " 1 "]))))
@example(record={"d03": "nan"})
@example(record={"d03": "1e308"})
@example(record={"A1x": " 1 ", "d01": ""})
def test_a_damaged_or_hostile_controller_record_is_refused_in_words(record):
    """Whatever a recording's controller_config record holds, the parameters come back
    checked (finite, a mechanism) or refused with a reason; never an exception. The
    drawn keys overwrite a whole record of the reference geometry, so most examples have
    all 20 parameters."""
    from loopcal.daemon.config.controller import nominal_config, params_from_metadata

    params, why = params_from_metadata({**nominal_config().as_metadata(), **record})
    if params is None:
        assert why.startswith("its controller_config record") or why.startswith("the file has")
    else:
        assert why == "" and params.shape == (20,) and np.all(np.isfinite(params))

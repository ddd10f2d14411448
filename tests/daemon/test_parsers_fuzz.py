"""Every parser of outside input, fuzzed with hypothesis: for any input it returns a value
or raises its own documented error, never anything else.

- the ASCII protocol's answer parser (bytes off the wire): DAQProtocolError or
  DAQInvalidCommand;
- the driver URL parser (a string from a config or the command line): ValueError;
- the daemon's TOML config and the controller config (files people edit): SettingsError
  and ControllerConfigError, each naming the file.
- the command line's numbers (``--speed``, ``--target-mm``): the number typed, in its
  range, or argparse's ArgumentTypeError naming what was typed.

(The recording reader has its own fuzz in tests/daemon/recording/test_damage.py;
bench/fuzz_parsers.py runs those of files and the wire for longer and prints counts per
outcome.)
"""

from __future__ import annotations

import argparse
import math
import string

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from loopcal.daemon.commands.guidance_display import target_mm_argument
from loopcal.daemon.config.controller import (
    ControllerConfigError,
    load_controller_config,
    render_initial_config,
)
from loopcal.daemon.live.guidance_defaults import MAX_TARGET_MM
from loopcal.daemon.recorder.settings import SettingsError, load_daemon_config
from loopcal.drivers import DAQInvalidCommand, DAQProtocolError, driver_for_url
from loopcal.drivers import ascii as ascii_proto
from loopcal.simulator.arguments import speed_argument
from tests.support.fuzz import examples
from tests.support.mutations import ASCII_ANSWERS, DAEMON_TOML

_FIXTURE = [HealthCheck.function_scoped_fixture]


def _answer_bytes():
    near = st.sampled_from(ASCII_ANSWERS).flatmap(
        lambda a: st.tuples(st.just(a), st.integers(0, len(a)), st.binary(max_size=4)).map(
            lambda t: t[0][: t[1]] + t[2] + t[0][t[1] + len(t[2]) :]
        )
    )
    return st.one_of(near, st.binary(max_size=48))


@pytest.mark.slow
@settings(max_examples=examples(400), deadline=None)
@given(line=_answer_bytes(), checksum=st.booleans(), addr=st.integers(0, 255))
def test_ascii_answers_parse_or_raise_protocol_errors(line, checksum, addr):
    try:
        body = ascii_proto.unframe(line, checksum=checksum)
    except DAQProtocolError:
        return
    for parse in (ascii_proto.parse_scan, ascii_proto.parse_channel):
        try:
            parse(body, addr)
        except (DAQProtocolError, DAQInvalidCommand):
            pass
    try:
        payload = ascii_proto.parse_ack(body, addr)
    except (DAQProtocolError, DAQInvalidCommand):
        return
    for parse in (ascii_proto.parse_firmware, ascii_proto.parse_rate):
        try:
            parse(payload)
        except DAQProtocolError:
            pass


_URL_PARTS = st.sampled_from(["modbus-tcp://", "modbus-rtu://", "ascii://", "MODBUS-TCP://",
                              "x://", "", "modbus-tcp:", "ascii:///dev/"])  # fmt: skip
_QUERY = st.lists(
    st.tuples(
        st.sampled_from(
            ["unit", "fifo", "baud", "addr", "checksum", "parity", "stopbits", "x", ""]
        ),  # fmt: skip
        st.text(max_size=8),
    ),
    max_size=4,
).map(lambda kv: "&".join(f"{k}={v}" for k, v in kv))


@pytest.mark.slow
@settings(max_examples=examples(400), deadline=None)
@given(
    head=_URL_PARTS,
    middle=st.text(alphabet=string.printable + "é\x00", max_size=24),
    query=_QUERY,
)
def test_driver_urls_parse_or_raise_value_error(head, middle, query):
    url = f"{head}{middle}?{query}" if query else head + middle
    try:
        cls, parsed = driver_for_url(url)
    except ValueError:
        return
    assert parsed.scheme == cls.scheme


_CONTROLLER = render_initial_config()


def _toml_like(base: str):
    """Text near a valid config: a line replaced, a value changed, bytes spliced in."""
    lines = base.splitlines()
    return st.one_of(
        st.tuples(st.integers(0, len(lines) - 1), st.text(max_size=40)).map(
            lambda t: "\n".join(lines[: t[0]] + [t[1]] + lines[t[0] + 1 :])
        ),
        st.tuples(st.integers(0, len(base)), st.text(max_size=12)).map(
            lambda t: base[: t[0]] + t[1] + base[t[0] :]
        ),
        st.text(max_size=200),
    ).map(lambda s: s.encode("utf-8", errors="surrogatepass"))


@pytest.mark.slow
@settings(max_examples=examples(250), deadline=None, suppress_health_check=_FIXTURE)
@given(data=st.one_of(_toml_like(_CONTROLLER), st.binary(max_size=300)))
def test_controller_configs_load_or_raise_their_error(tmp_path, data):
    path = tmp_path / "controller.toml"
    path.write_bytes(data)
    try:
        load_controller_config(path)
    except ControllerConfigError as exc:
        assert str(path) in str(exc)


def _daemon_with(old: str, new: str) -> bytes:
    return DAEMON_TOML.replace(old, new).encode()


@settings(max_examples=examples(250), deadline=None, suppress_health_check=_FIXTURE)
@given(data=st.one_of(_toml_like(DAEMON_TOML), st.binary(max_size=300)))
@example(data=_daemon_with('"256 MiB"', '"' + "9" * 400 + ' TiB"'))  # was OverflowError
@example(data=_daemon_with('"/etc/loopcal/controller/controller.toml"', '"\\u0000"'))
@example(data=_daemon_with('"/var/lib/loopcal/recordings"', '"/var/\\u0000x"'))
@example(data=_daemon_with("?unit=1", "?unit=1\\u0000"))
@example(data=_daemon_with("500000", "99999999999999999999"))
def test_daemon_configs_load_or_raise_their_error(tmp_path, data):
    path = tmp_path / "daemon.toml"
    path.write_bytes(data)
    try:
        load_daemon_config(path)
    except SettingsError as exc:
        assert str(path) in str(exc)


def test_the_fuzzed_daemon_config_sets_every_key():
    """A key the fuzzer's config leaves out is never mutated: every setting is in it."""
    import tomllib

    from loopcal.daemon.recorder.settings import SETTINGS

    doc = tomllib.loads(DAEMON_TOML)
    written = {f"[{table}].{key}" for table, keys in doc.items() for key in keys}
    assert {s.key for s in SETTINGS.values() if s.key} == written


def _number_texts():
    numbers = st.floats(allow_nan=True, allow_infinity=True).map(repr)
    return st.one_of(numbers, st.sampled_from(["0", "-0", "1e309", "nan", "inf", "10", "10.0001",
                                               " 2 ", "0x10", "1_0", ""]), st.text(max_size=12))


@settings(max_examples=examples(300), deadline=None)
@given(text=_number_texts())
@example(text="10")
@example(text="1e-300")
@example(text="-1")
def test_command_line_numbers_parse_or_raise_argparse_errors(text):
    for parse, hi in ((speed_argument, math.inf), (target_mm_argument, MAX_TARGET_MM)):
        try:
            value = parse(text)
        except argparse.ArgumentTypeError as exc:
            assert repr(text) in str(exc)  # names what was typed
            try:  # refused: not a number of its range, by Python's own float()
                assert not (0 < float(text) <= hi and math.isfinite(float(text)))
            except ValueError:
                pass
        else:
            assert value == float(text) and 0 < value <= hi and math.isfinite(value)

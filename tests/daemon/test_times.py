"""One spelling of a time and a duration (daemon/times.py): what a command prints, an
option takes back, to the millisecond it shows."""

from __future__ import annotations

import re
from datetime import UTC, datetime

import pytest
from hypothesis import given
from hypothesis import strategies as st

from loopcal.daemon.times import (
    name_stamp,
    parse_duration,
    parse_time,
    span_text,
    time_json,
    time_or,
    time_text,
)

SPELLING = re.compile(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z$")
MS = 1_000_000
# 1970 to 9999: what a datetime holds
NS = st.integers(min_value=0, max_value=253_402_300_799 * 10**9)


@given(NS)
def test_a_printed_time_reads_back_to_the_millisecond_it_shows(ns: int) -> None:
    text = time_text(ns)
    assert SPELLING.match(text), text
    assert parse_time(text) == ns - ns % MS  # truncated, never rounded up


def test_the_spelling() -> None:
    ns = int(datetime(2026, 12, 3, 8, 37, 37, 357_999, tzinfo=UTC).timestamp()) * 10**9 \
        + 357_999_999
    assert time_text(ns) == "2026-12-03T08:37:37.357Z"
    assert time_json(None) is None and time_json(ns) == time_text(ns)
    assert time_or(None) == "?" and time_or(None, "-") == "-"
    assert span_text(ns, ns + 10**9) == "2026-12-03T08:37:37.357Z to 2026-12-03T08:37:38.357Z"
    assert span_text(None, ns) == ""
    assert time_text(10**30) == f"{10**30} ns"  # a damaged stamp is shown, not hidden
    assert re.match(r"^\d{8}T\d{6}Z$", name_stamp())
    assert name_stamp(ns) == "20261203T083737Z"


@pytest.mark.parametrize("text", [
    "2026-12-03T08:37:37.357Z",
    "2026-12-03T08:37:37.357+00:00",
    "2026-12-03T09:37:37.357+01:00",
    "2026-12-03 08:37:37.357",
    "2026-12-03 08:37:37.357 UTC",  # what `info` printed before
    "2026-12-03T08:37:37.357",
])
def test_every_iso_spelling_of_one_instant_is_taken(text: str) -> None:
    assert time_text(parse_time(text)) == "2026-12-03T08:37:37.357Z"


def test_a_date_alone_is_its_midnight_utc() -> None:
    assert time_text(parse_time("2026-12-03")) == "2026-12-03T00:00:00.000Z"


@pytest.mark.parametrize("text", ["", "yesterday", "2026-13-01", "12:00", "2026-12-03 UTC+1"])
def test_what_is_not_a_time_is_refused_by_name(text: str) -> None:
    with pytest.raises(ValueError, match=re.escape(repr(text))):
        parse_time(text)


@pytest.mark.parametrize(("text", "seconds"), [
    ("90", 90.0), ("90s", 90.0), ("1.5", 1.5), ("15m", 900.0), ("15min", 900.0),
    ("2h", 7200.0), ("1d", 86400.0), (" 3 s ", 3.0), (".5", 0.5),
])  # fmt: skip
def test_a_duration_is_seconds_or_a_number_with_a_unit(text: str, seconds: float) -> None:
    assert parse_duration(text) == seconds


@pytest.mark.parametrize("text", ["", "0", "0s", "-5", "5 weeks", "inf", "nan", "1e400", "s"])
def test_what_is_not_a_duration_is_refused_by_name(text: str) -> None:
    with pytest.raises(ValueError, match=re.escape(repr(text))):
        parse_duration(text)


@given(st.text(max_size=40))
def test_any_text_is_a_time_or_a_clear_refusal(text: str) -> None:
    try:
        ns = parse_time(text)
    except ValueError as exc:
        assert repr(text) in str(exc)
    else:
        assert isinstance(ns, int)

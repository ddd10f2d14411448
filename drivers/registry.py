"""URL scheme -> driver class: :func:`open_daq` and :func:`driver_for_url` pick a driver by
the scheme of a URL (:mod:`loopcal.drivers.url`), as python-can picks an interface.

The drivers are found in two places:

- the entry point group ``loopcal.drivers`` (:data:`ENTRY_POINT_GROUP`): each entry point's
  name is a scheme, its object a :class:`~loopcal.drivers.base.DAQ` subclass. loopcal's own
  transports are declared there (pyproject.toml), and so is a third party's: a package
  installed beside loopcal adds a scheme without editing it. The group is read on first
  need (importlib.metadata), and a driver is imported when its scheme is first asked for
  (pymodbus and pyserial come with the built-in ones);
- :func:`register_scheme`, a class decorator for a driver defined in a program.

A scheme claimed twice (by two packages, or by a package and :func:`register_scheme`), or
an entry point that fails to load, is a :class:`DriverLoadError` naming the package(s),
raised when the scheme is asked for. :func:`open_daq` parses the URL, rejects unknown query
parameters, and hands the parsed URL to the driver class.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points

from . import ldq412
from .base import DAQ, D
from .url import DaqUrl, parse_url

#: the entry point group a package declares its drivers in (pyproject.toml:
#: ``[project.entry-points."loopcal.drivers"]``, ``myscheme = "mypackage.module:MyDAQ"``)
ENTRY_POINT_GROUP = "loopcal.drivers"


class DriverLoadError(ValueError):
    """A scheme's driver cannot be had: two packages claim the scheme, or its entry point
    fails to load or names no :class:`~loopcal.drivers.base.DAQ` subclass.

    A ValueError, as is any URL no driver takes (a settings check reports it against the
    URL); the message names the package(s) and the entry point(s).
    """


@dataclass(frozen=True, slots=True)
class _Claim:
    """One claim on a scheme: who makes it, and the object it names."""

    who: str  # "package mypkg 1.0" or "register_scheme"
    target: str  # "module:qualname"
    entry_point: EntryPoint | None = None


#: register_scheme's classes, by scheme
_REGISTERED: dict[str, type[DAQ]] = {}
#: the class each scheme asked for so far resolved to
_RESOLVED: dict[str, type[DAQ]] = {}


def _target(cls: type) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


def _claims() -> dict[str, list[_Claim]]:
    """Every claim on every scheme: the entry points of :data:`ENTRY_POINT_GROUP` (read now,
    so a package put on the path since is seen) and :func:`register_scheme`'s classes."""
    out: dict[str, list[_Claim]] = {}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        dist = ep.dist
        who = f"package {dist.name} {dist.version}" if dist is not None else "an unnamed package"
        out.setdefault(ep.name, []).append(_Claim(who, ep.value.replace(" ", ""), ep))
    for scheme, cls in _REGISTERED.items():
        out.setdefault(scheme, []).append(_Claim("register_scheme", _target(cls)))
    return out


def _load(scheme: str, claim: _Claim) -> type[DAQ]:
    """The class an entry point names, checked to be a DAQ subclass for ``scheme``."""
    assert claim.entry_point is not None
    where = f"entry point {scheme} = {claim.target} of {claim.who} (group {ENTRY_POINT_GROUP})"
    try:
        cls = claim.entry_point.load()
    except Exception as exc:  # noqa: BLE001 - whatever a foreign package raises, say whose it is
        raise DriverLoadError(
            f"the driver for {scheme}:// cannot be loaded: {where}: {type(exc).__name__}: {exc}"
        ) from exc
    if not (isinstance(cls, type) and issubclass(cls, DAQ)):
        raise DriverLoadError(f"{where} names {cls!r}, not a subclass of loopcal's DAQ")
    own = cls.__dict__.get("scheme")
    if own not in (None, "", scheme):
        raise DriverLoadError(f"{where} names a class whose scheme is {own!r}")
    cls.scheme = scheme
    return cls


def _resolve(scheme: str) -> type[DAQ] | None:
    """The driver class of ``scheme``, loaded on first need; None if nothing claims it.

    Raises
    ------
    DriverLoadError
        If more than one object claims the scheme, or its entry point fails to load.
    """
    cls = _RESOLVED.get(scheme)
    if cls is not None:
        return cls
    claims = _claims().get(scheme, [])
    if not claims:
        return None
    if len({c.target for c in claims}) > 1:
        named = "; ".join(f"{c.target} by {c.who}" for c in claims)
        raise DriverLoadError(
            f"URL scheme {scheme!r} is claimed more than once: {named} (uninstall one of "
            "the packages, or rename its scheme)"
        )
    claim = claims[0]
    cls = _REGISTERED[scheme] if claim.entry_point is None else _load(scheme, claim)
    _RESOLVED[scheme] = cls
    return cls


def register_scheme(scheme: str) -> Callable[[type[D]], type[D]]:
    """Class decorator: make :func:`open_daq` open URLs of ``scheme`` with the class.

    For a driver defined in a program; a package declares its drivers as entry points
    instead (:data:`ENTRY_POINT_GROUP`), so that they load only when their scheme is used.

    Parameters
    ----------
    scheme : str
        The URL scheme, lower case (e.g. ``"modbus-tcp"``); set as the class's
        :attr:`DAQ.scheme`.

    Returns
    -------
    Callable[[type[DAQ]], type[DAQ]]
        The decorator; it returns the class unchanged.

    Raises
    ------
    ValueError
        When the decorator is applied, if another class has registered ``scheme`` or was
        opened for it. A package's entry point for the same scheme is a
        :class:`DriverLoadError` when the scheme is asked for.
    """

    def deco(cls: type[D]) -> type[D]:
        for taken in (_REGISTERED.get(scheme), _RESOLVED.get(scheme)):
            if taken is not None and taken is not cls:
                raise ValueError(f"URL scheme {scheme!r} already registered ({_target(taken)})")
        _REGISTERED[scheme] = cls
        cls.scheme = scheme
        return cls

    return deco


def registered_schemes() -> dict[str, type[DAQ]]:
    """Every scheme a driver is declared or registered for, each driver loaded.

    Returns
    -------
    dict[str, type[DAQ]]
        Scheme -> driver class (a copy).

    Raises
    ------
    DriverLoadError
        If a scheme is claimed twice or an entry point fails to load.
    """
    out = {}
    for scheme in sorted(_claims()):
        cls = _resolve(scheme)
        if cls is not None:
            out[scheme] = cls
    return out


def _unknown_scheme(scheme: str) -> ValueError:
    known = sorted(_claims())
    if not known:  # not even loopcal's own: an install without its metadata
        return ValueError(
            f"unknown DAQ URL scheme {scheme!r} (known: none; loopcal's own drivers are "
            f"declared in the entry point group {ENTRY_POINT_GROUP!r}, which is missing: "
            "reinstall loopcal, pip install -e . in a checkout)"
        )
    return ValueError(f"unknown DAQ URL scheme {scheme!r} (known: {', '.join(known)})")


def driver_for_url(url: str) -> tuple[type[DAQ], DaqUrl]:
    """The driver class a URL names and the parsed URL, every value checked, without
    connecting.

    Parameters
    ----------
    url : str
        A driver URL (see :func:`parse_url` and the drivers' docstrings).

    Returns
    -------
    tuple[type[DAQ], DaqUrl]
        The driver class registered for the URL's scheme, and the parsed URL.

    Raises
    ------
    ValueError
        For a malformed URL, an unknown scheme (naming the known ones), a query parameter
        the driver does not take (naming those it takes), or a value out of range.
    DriverLoadError
        A ValueError: the scheme is claimed twice, or its entry point fails to load.
    """
    parsed = parse_url(url)
    cls = _resolve(parsed.scheme)
    if cls is None:
        raise _unknown_scheme(parsed.scheme)
    unknown = set(parsed.params) - set(cls.url_params)
    if unknown:
        raise ValueError(
            f"{url}: unknown parameter(s) {sorted(unknown)} for {parsed.scheme} "
            f"(allowed: {sorted(cls.url_params)})"
        )
    cls.url_options(parsed)  # every value checked now, not when the driver connects
    return cls, parsed


def open_daq(
    url: str, *, timeout: float = ldq412.HOST_TIMEOUT_S, check_identity: bool = True
) -> DAQ:
    """Open the driver the URL's scheme names and connect to the module.

    Parameters
    ----------
    url : str
        ``modbus-tcp://host[:port]?unit=1[&fifo=1]``,
        ``modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1[&parity=N&stopbits=1&fifo=1]`` or
        ``ascii:///dev/ttyUSB0?baud=115200&addr=01&checksum=0``.
    timeout : float
        s without an answer before a call raises DAQTimeout (> 0; datasheet: 0.1 s).
    check_identity : bool
        Raise DAQIdentityError unless the module identifies as an LDQ-412.

    Returns
    -------
    DAQ
        The connected driver (a context manager: ``with open_daq(url) as daq: ...``).

    Raises
    ------
    ValueError
        For a malformed URL, an unknown scheme, an unknown or bad query parameter, or a
        timeout that is not > 0; :class:`DriverLoadError` for a scheme claimed twice or a
        driver that fails to load.
    DAQError
        The driver's subclasses: DAQDisconnected (cannot connect), DAQTimeout (no answer
        at connect), DAQProtocolError, DAQIdentityError (not an LDQ-412).
    """
    cls, parsed = driver_for_url(url)
    if not timeout > 0:
        raise ValueError(f"timeout must be > 0 s, got {timeout}")
    return cls.from_url(parsed, timeout=timeout, check_identity=check_identity)

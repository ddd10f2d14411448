"""URL scheme -> driver class: :func:`open_daq` and :func:`driver_for_url` pick a driver by
the scheme of a URL (:mod:`loopcal.drivers.url`), as python-can picks an interface.

Drivers register their scheme with :func:`register_scheme`; :func:`open_daq` parses the
URL, rejects unknown query parameters, and hands the parsed URL to the driver class.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

from . import ldq412
from .base import DAQ, D
from .url import DaqUrl, parse_url

_REGISTRY: dict[str, type[DAQ]] = {}


def register_scheme(scheme: str) -> Callable[[type[D]], type[D]]:
    """Class decorator: make :func:`open_daq` open URLs of ``scheme`` with the class.

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
        When the decorator is applied, if another class has registered ``scheme``.
    """

    def deco(cls: type[D]) -> type[D]:
        if scheme in _REGISTRY and _REGISTRY[scheme] is not cls:
            raise ValueError(f"URL scheme {scheme!r} already registered")
        _REGISTRY[scheme] = cls
        cls.scheme = scheme
        return cls

    return deco


#: the modules of the drivers that come with loopcal; each registers its scheme on import
_BUILTIN = ("loopcal.drivers.modbus_tcp", "loopcal.drivers.modbus_rtu", "loopcal.drivers.ascii")


def _load_builtin() -> None:
    """Import the built-in drivers (on first need: they bring pymodbus and pyserial)."""
    for module in _BUILTIN:
        importlib.import_module(module)


def registered_schemes() -> dict[str, type[DAQ]]:
    """The registered drivers, the built-in ones imported first.

    Returns
    -------
    dict[str, type[DAQ]]
        Scheme -> driver class (a copy).
    """
    _load_builtin()
    return dict(_REGISTRY)


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
    """
    parsed = parse_url(url)
    if parsed.scheme not in _REGISTRY:
        _load_builtin()
    try:
        cls = _REGISTRY[parsed.scheme]
    except KeyError:
        known = ", ".join(sorted(_REGISTRY))
        raise ValueError(f"unknown DAQ URL scheme {parsed.scheme!r} (known: {known})") from None
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
        timeout that is not > 0.
    DAQError
        The driver's subclasses: DAQDisconnected (cannot connect), DAQTimeout (no answer
        at connect), DAQProtocolError, DAQIdentityError (not an LDQ-412).
    """
    cls, parsed = driver_for_url(url)
    if not timeout > 0:
        raise ValueError(f"timeout must be > 0 s, got {timeout}")
    return cls.from_url(parsed, timeout=timeout, check_identity=check_identity)

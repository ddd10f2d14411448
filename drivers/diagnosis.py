"""Why a module cannot be reached, in words: :func:`diagnose` turns a driver's error into a
:class:`Diagnosis` (a cause code, what is wrong, what to do), without a byte on the wire.

It reads what the error carries (a driver's :class:`~loopcal.drivers.errors.DAQError` is
chained, ``__cause__``, from the socket's or the serial port's own error, whose errno
tells a closed port from a host that does not answer) and, for a serial line, what the
device node says: :func:`port_problem` stats and opens it (without sending anything) to
tell a missing device from one the user may not open or one another process holds. A
serial line behind a serial device server (``ascii://HOST:PORT``, :mod:`loopcal.drivers.url`)
is a TCP connection to the device server as far as reaching it goes, and a serial line
for the rest (:func:`server_problem` opens a connection to it for a moment). A recorder
asks it while the module is unreachable, and ``loopcal probe``
(:mod:`loopcal.drivers.probe`) for the failures it does not find out by trying.

The causes (:data:`CAUSES`) are codes a program may test; the message and the hint are for
people.
"""

from __future__ import annotations

import errno
import fcntl
import grp
import os
import pwd
import socket
import stat
from dataclasses import dataclass, field
from pathlib import Path

from . import errors, ldq412
from .registry import driver_for_url
from .url import device_server, host_port

#: every cause code, and what it means (docs/hardware.md shows an example of each)
CAUSES: dict[str, str] = {
    "refused": "nothing listens at the host's port (connection refused)",
    "timeout": "the host does not answer (the TCP connection timed out)",
    "unreachable": "no route to the host, or its network is down",
    "unknown_host": "the host name does not resolve",
    "closed": "the host accepts the connection but closes it on a Modbus request",
    "not_modbus": "something answers, but not Modbus (or not the ASCII protocol)",
    "not_module": "a device answers, but it is not an LDQ-412",
    "no_answer": "the connection or port opens, but nothing answers",
    "wrong_unit": "the Modbus unit id does not answer; another does",
    "wrong_address": "the ASCII address does not answer; another does",
    "wrong_checksum": "the ASCII checksum mode is not the module's",
    "wrong_baud": "the line rate is not the module's; another rate answers",
    "garbled": "bytes arrive on the serial line, but no valid frame",
    "no_device": "no such serial device",
    "not_a_device": "the path is not a serial device",
    "permission": "permission denied on the serial device",
    "busy": "the device or module is held by another process",
    "lost": "the connection was lost (reset, closed, or the port went away)",
    "error": "another error",
}


@dataclass(frozen=True)
class Diagnosis:
    """Why a module cannot be reached, or where it answers instead.

    Attributes
    ----------
    cause : str
        One of :data:`CAUSES`.
    message : str
        What is wrong, one sentence naming the endpoint (``nothing listens at
        127.0.0.1:502 (connection refused)``).
    hint : str
        What to do about it.
    details : dict
        Facts behind the message, JSON-ready: the serial ports that exist, the device's
        group, the pids holding a port, the bytes a non-Modbus server sent, ...
    """

    cause: str
    message: str
    hint: str
    details: dict = field(default_factory=dict)

    def line(self) -> str:
        """The message and the hint as one line of a log (``MESSAGE [cause]; HINT``).

        Returns
        -------
        str
        """
        return f"{self.message} [{self.cause}]; {self.hint}"


def errno_of(exc: BaseException) -> tuple[int | None, BaseException | None]:
    """The OS-level error in an exception's chain (``__cause__``, else ``__context__``)
    that says what happened, and its errno.

    Parameters
    ----------
    exc : BaseException
        A driver's error, as raised.

    Returns
    -------
    tuple of (int or None, BaseException or None)
        The first OSError in the chain that has an errno, else the last OSError in it
        (pyserial's SerialException is one, often without an errno: ``Could not open
        port socket://...`` has the socket's ConnectionRefusedError or TimeoutError as its
        ``__context__``), and its errno (None for a timeout or a name that does not
        resolve, which have none that says it); (None, None) if the chain holds none.
    """
    seen: set[int] = set()
    found: OSError | None = None
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OSError) and not isinstance(e, errors.DAQError):
            if e.errno is not None:
                return e.errno, e
            found = e
        e = e.__cause__ or e.__context__
    return None, found


def serial_ports() -> list[str]:
    """The serial ports this host has: pyserial's list (from sysfs), then the stable names
    under ``/dev/serial/by-id`` with what each points to.

    Returns
    -------
    list of str
        E.g. ``["/dev/ttyS0", "/dev/ttyUSB0 (FT232R USB UART)",
        "/dev/serial/by-id/usb-FTDI_FT232R_A1B2-if00-port0 -> /dev/ttyUSB0"]``.
    """
    out = []
    try:
        from serial.tools import list_ports

        for port in sorted(list_ports.comports(), key=lambda p: p.device):
            described = port.description not in (None, "", "n/a", port.name)
            out.append(f"{port.device} ({port.description})" if described else port.device)
    except Exception:  # noqa: BLE001 - a list for a message: what is there, never an error
        pass
    by_id = Path("/dev/serial/by-id")
    try:
        for link in sorted(by_id.iterdir()):
            out.append(f"{link} -> {os.path.realpath(link)}")
    except OSError:
        pass
    return out


def port_holders(path: str) -> list[tuple[int, str]]:
    """The processes that have a device open, as far as /proc lets this user see.

    Parameters
    ----------
    path : str
        The device (its symlinks resolved).

    Returns
    -------
    list of (int, str)
        ``(pid, command line)`` of each, this process left out.
    """
    target = os.path.realpath(path)
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        try:
            fds = list((proc / "fd").iterdir())
        except OSError:
            continue
        for fd in fds:
            try:
                opened = os.readlink(fd)
            except OSError:
                continue
            if opened == target:
                found.append((int(proc.name), _command_line(int(proc.name))))
                break
    return found


def lock_holders(path: str) -> list[int]:
    """The processes holding a ``flock`` on a device (pyserial's and pymodbus' exclusive
    open takes one), from /proc/locks.

    Parameters
    ----------
    path : str
        The device.

    Returns
    -------
    list of int
        Their pids (this process's own left out).
    """
    try:
        st = os.stat(path)
        table = Path("/proc/locks").read_text()
    except OSError:
        return []
    node = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    pids = []
    for row in table.splitlines():
        words = row.split()  # "1: FLOCK ADVISORY WRITE 1234 00:19:6 0 EOF"
        if len(words) >= 6 and words[1] == "FLOCK" and words[5] == node:
            pid = int(words[4])
            if pid != os.getpid() and pid not in pids:
                pids.append(pid)
    return pids


def _command_line(pid: int) -> str:
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return ""
    return raw.replace(b"\0", b" ").decode(errors="replace").strip()


def _user() -> str:
    try:
        return pwd.getpwuid(os.geteuid()).pw_name
    except KeyError:
        return str(os.geteuid())


def _permission(path: str, st: os.stat_result) -> Diagnosis:
    """EACCES on a device: whose it is, and whether this user is in its group."""
    mode = stat.filemode(st.st_mode)
    try:
        group = grp.getgrgid(st.st_gid).gr_name
        members = set(grp.getgrgid(st.st_gid).gr_mem)
    except KeyError:
        group, members = str(st.st_gid), set()
    user = _user()
    in_session = st.st_gid in os.getgroups() or st.st_gid == os.getegid()
    try:
        listed = user in members or pwd.getpwnam(user).pw_gid == st.st_gid
    except KeyError:
        listed = False
    details = {
        "device": path,
        "mode": mode,
        "group": group,
        "user": user,
        "in_group": in_session,
        "listed_in_group": listed,
    }
    message = f"permission denied on {path} ({mode}, group {group})"
    if not st.st_mode & stat.S_IRGRP or not st.st_mode & stat.S_IWGRP:
        hint = (
            f"its group {group} may not read and write it either: a udev rule must give "
            f"it to a group (dialout, as serial ports usually are) with mode 0660"
        )
    elif listed and not in_session:
        hint = (
            f"user {user} is in group {group}, but not in this session: log in again "
            "(or run `newgrp " + group + "`)"
        )
    elif in_session:
        hint = f"user {user} is in group {group}, yet may not open it: an ACL or a security module?"
    else:
        hint = (
            f"user {user} is not in group {group}: `sudo usermod -aG {group} {user}`, then "
            "log in again (the loopcal service's user is in dialout already)"
        )
    return Diagnosis("permission", message, hint, details)


def _busy(path: str, how: str) -> Diagnosis:
    locked = lock_holders(path) if how == "locked" else []
    holders = [(pid, _command_line(pid)) for pid in locked] or port_holders(path)
    named = "; ".join(f"pid {pid}" + (f" ({cmd})" if cmd else "") for pid, cmd in holders)
    message = f"{path} is held by another process ({how})" + (f": {named}" if named else "")
    hint = (
        "stop it, or close the program holding the port (minicom, screen, a serial "
        "monitor, another loopcal)"
        if holders
        else "another user's process holds it (not visible here): `sudo fuser -v " + path + "`"
    )
    return Diagnosis(
        "busy",
        message,
        hint,
        {"device": path, "holders": [{"pid": p, "command": c} for p, c in holders]},
    )


def port_problem(path: str) -> Diagnosis | None:
    """What is wrong with a serial device as a device, found by looking at it and opening it
    for a moment (no byte is sent): missing, not a device, not ours to open, held.

    Parameters
    ----------
    path : str
        The serial device, e.g. ``/dev/ttyUSB0`` (a symlink is followed).

    Returns
    -------
    Diagnosis or None
        ``no_device`` (naming the ports there are), ``not_a_device``, ``permission``
        (naming its group and whether the user is in it) or ``busy`` (naming the
        processes that hold it); None if it opens and nobody holds it.
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        ports = serial_ports()
        there = ", ".join(ports) if ports else "none"
        return Diagnosis(
            "no_device",
            f"no such device {path}; serial ports here: {there}",
            "plug the adapter in and see its name in `dmesg | tail` (ttyUSB*, ttyACM*), or "
            "use its stable name under /dev/serial/by-id",
            {"device": path, "ports": ports},
        )
    except PermissionError as exc:
        return Diagnosis(
            "permission",
            f"permission denied on {path}: {exc.strerror}",
            "a directory on the way may not be searched by this user",
            {"device": path},
        )
    except OSError as exc:
        return Diagnosis(
            "no_device", f"{path}: {exc.strerror}", "is it the right path?", {"device": path}
        )
    if not stat.S_ISCHR(st.st_mode):
        kind = "a directory" if stat.S_ISDIR(st.st_mode) else "not a character device"
        return Diagnosis(
            "not_a_device",
            f"{path} is not a serial device ({kind})",
            "name the serial port, e.g. /dev/ttyUSB0 or a /dev/serial/by-id name",
            {"device": path, "ports": serial_ports()},
        )
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK | os.O_CLOEXEC)
    except PermissionError:
        return _permission(path, st)
    except OSError as exc:
        if exc.errno == errno.EBUSY:
            return _busy(path, "opened exclusively")
        if exc.errno in (errno.ENXIO, errno.ENODEV, errno.EIO):
            return Diagnosis(
                "no_device",
                f"{path} exists but no device answers behind it ({exc.strerror})",
                "is the adapter plugged in? `dmesg | tail`",
                {"device": path, "ports": serial_ports()},
            )
        return Diagnosis("error", f"{path}: {exc.strerror}", "see `dmesg | tail`", {"device": path})
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return _busy(path, "locked")
    except OSError:
        pass  # a device that cannot be locked: nobody holds it that way
    finally:
        os.close(fd)
    return None


@dataclass(frozen=True)
class Endpoint:
    """What a driver URL reaches (:func:`endpoint`).

    Attributes
    ----------
    where : str
        For messages: ``HOST:PORT`` of a TCP connection (Modbus TCP's, or a serial device
        server's), else the serial device.
    options : dict
        The driver's options (:meth:`~loopcal.drivers.base.DAQ.url_options`).
    serial : bool
        A serial line (Modbus RTU, ASCII), on a device or behind a device server.
    server : tuple of (str, int) or None
        The serial device server's host and TCP port, for a line reached through one
        (:func:`~loopcal.drivers.url.device_server`).
    """

    where: str
    options: dict
    serial: bool
    server: tuple[str, int] | None

    @property
    def device(self) -> bool:
        """A serial device of this host (which :func:`port_problem` can look at)."""
        return self.serial and self.server is None


def endpoint(url: str) -> Endpoint:
    """What a driver URL reaches, for messages and for what to look at.

    Parameters
    ----------
    url : str
        A driver URL.

    Returns
    -------
    Endpoint

    Raises
    ------
    ValueError
        For a URL no driver takes (as :func:`~loopcal.drivers.registry.driver_for_url`).
    """
    cls, parsed = driver_for_url(url)
    options = cls.url_options(parsed)
    if isinstance(options.get("host"), str):
        return Endpoint(host_port(options["host"], options["port"]), options, False, None)
    server = device_server(str(options["port"]))
    where = host_port(*server) if server else str(options["port"])
    return Endpoint(where, options, True, server)


def _socket_error(
    where: str, code: int | None, err: BaseException, timeout: float, *, server: bool = False
) -> Diagnosis:
    """A TCP connection that failed, by its OS error (``server``: a serial device server's)."""
    device = "device server" if server else "module"
    if code == errno.ECONNREFUSED:
        return Diagnosis(
            "refused",
            f"nothing listens at {where} (connection refused)",
            "is the device server powered, is this its address, and is this the TCP port of "
            "the module's serial port, in raw TCP server mode? (a Moxa NPort's first is 4001)"
            if server
            else "is the module powered, and is this its address? Modbus TCP is port "
            f"{ldq412.MODBUS_TCP_PORT}; another device may have the address",
        )
    if isinstance(err, socket.gaierror):
        return Diagnosis(
            "unknown_host",
            f"the host of {where} is not known ({err.strerror})",
            f"check the name, or give the {device}'s IP address",
        )
    if isinstance(err, TimeoutError) or code == errno.ETIMEDOUT:
        return Diagnosis(
            "timeout",
            f"{where} does not answer (no TCP connection within {timeout:g} s)",
            f"is the {device} powered and on this network? "
            "`ping` its address; a firewall may drop the connection",
        )
    if code in (errno.EHOSTUNREACH, errno.ENETUNREACH, errno.ENETDOWN, errno.EHOSTDOWN):
        return Diagnosis(
            "unreachable",
            f"no route to {where} ({os.strerror(code)})",
            f"is this host on the {device}'s network (cable, address, routes)?",
        )
    if code in (errno.ECONNRESET, errno.EPIPE, errno.ECONNABORTED):
        return Diagnosis(
            "lost",
            f"the connection to {where} was reset ({os.strerror(code)})",
            "the device server restarting, or taking the port for another client"
            if server
            else "the module restarting, or another master taking its one connection",
        )
    what = os.strerror(code) if code else str(err)
    return Diagnosis("error", f"cannot reach {where}: {what}", "see the message")


def _socket_line_connect_s() -> float:
    """s pyserial's ``socket://`` line waits for its TCP connection (its own, whatever the
    driver's timeout)."""
    from serial.urlhandler import protocol_socket

    return float(protocol_socket.POLL_TIMEOUT)


def server_problem(host: str, port: int, timeout: float) -> Diagnosis | None:
    """What keeps a serial device server's TCP port from being reached, found by opening a
    connection to it for a moment (no byte is sent).

    Parameters
    ----------
    host : str
        The device server's host name or address.
    port : int
        The TCP port of the module's serial line.
    timeout : float
        s the connection may take.

    Returns
    -------
    Diagnosis or None
        ``refused``, ``timeout``, ``unreachable``, ``unknown_host`` (or ``error``), naming
        ``HOST:PORT``; None if the connection opens.
    """
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return None
    except OSError as exc:
        return _socket_error(host_port(host, port), exc.errno, exc, timeout, server=True)


def diagnose(exc: BaseException, url: str, *, timeout: float = ldq412.HOST_TIMEOUT_S) -> Diagnosis:
    """Why the module at ``url`` is not reached, from the error a driver raised: no byte
    is sent (a serial device is looked at and opened for a moment, :func:`port_problem`).

    Parameters
    ----------
    exc : BaseException
        What the driver raised (a DAQError, its chain as it came).
    url : str
        The driver URL (valid: a driver took it).
    timeout : float
        The driver's timeout, s (for the messages).

    Returns
    -------
    Diagnosis
        Its cause, one of :data:`CAUSES`.
    """
    ep = endpoint(url)
    where, options, serial = ep.where, ep.options, ep.serial
    code, os_error = errno_of(exc)
    if isinstance(exc, errors.DAQDisconnected):
        if ep.device:
            found = port_problem(where)
            if found is not None:
                return found
            return Diagnosis(
                "lost",
                f"{where}: {exc}",
                "was the adapter unplugged? `dmesg | tail`",
                {"device": where},
            )
        cut = code is None and not isinstance(os_error, (TimeoutError, socket.gaierror))
        if ep.server and cut:  # pyserial's "socket disconnected": the device server hung up
            return Diagnosis(
                "lost",
                f"{where} closed the connection: {exc}",
                "the device server restarting, or taking the port for another client "
                "(how many it takes is its setting)",
            )
        if os_error is not None:
            waited = _socket_line_connect_s() if ep.server else timeout
            return _socket_error(where, code, os_error, waited, server=ep.server is not None)
        return Diagnosis(
            "closed",
            f"{where} accepts the connection but closes it without an answer",
            "not a Modbus TCP server, or one that takes no more clients "
            "(another master connected?)",
        )
    who = f"unit {options['unit']}" if "unit" in options else f"address {options['addr']:02X}"
    rate = f" at {options['baud']} baud" if ep.device else ""
    baud = (
        "the device server's baud rate (its own, not the URL's)" if ep.server else "the baud rate"
    )
    if isinstance(exc, errors.DAQIdentityError):
        return Diagnosis(
            "not_module",
            f"the device at {where} ({who}) is not an LDQ-412: {exc}",
            "is this the module's address? another device answers there",
        )
    if isinstance(exc, errors.DAQModbusException):
        return Diagnosis(
            "not_module",
            f"{who} at {where} refuses the LDQ-412's registers "
            f"(Modbus exception {exc.code:#04x}): {exc}",
            "another Modbus device answers at this unit id",
        )
    if isinstance(exc, errors.DAQProtocolError):
        if serial:
            return Diagnosis(
                "garbled",
                f"bytes arrive on {where}{rate} but no valid frame",
                f"{baud} or parity is not the module's, or another device talks on the line"
                + ("" if ep.server else ": `loopcal probe` tries the usual rates (with no "
                   "recorder running)"),
            )  # fmt: skip
        return Diagnosis(
            "not_modbus",
            f"something answers at {where}, but not a valid Modbus TCP answer: {exc}",
            "is this the module's address and port?",
        )
    if isinstance(exc, errors.DAQTimeout):
        if serial:
            hint = (
                f"the unit id or address, {baud} or the checksum mode may not be the "
                "module's (`loopcal probe` tries the others, with no recorder running), or the "
                "module is off or its RS-485 pair swapped"
            )
        else:
            hint = (
                "the unit id may not be the module's (`loopcal probe` tries the others, "
                "with no recorder running), or a gateway's serial side is down"
            )
        return Diagnosis(
            "no_answer", f"{who} does not answer at {where}{rate} within {timeout:g} s", hint
        )
    return Diagnosis("error", f"{where}: {type(exc).__name__}: {exc}", "see the message")

"""Technicians' sessions through the running daemon: the control socket's server.

``loopcal daemon`` owns the module (:mod:`loopcal.daemon.recorder.ownership`), so a
technician who calibrates after replacing a sensor asks the daemon for a session
(``loopcal session``) rather than open the module a second time. :class:`ControlServer`
listens on the daemon's control socket (:mod:`loopcal.daemon.live.control` is the
protocol), in a thread of its own: the recording never waits for it, whatever a client
sends or fails to read.

A session is the live guidance (:class:`loopcal.daemon.live.guidance.Guidance`) fed the
daemon's own scans from the moment it starts, through a :class:`SessionObserver` on the
recorder's analysis thread. Its scans are its *window* of the recording: the stamps of
the first and the last scan it was fed. It ends when the guidance finds the recording
enough (if asked), after its duration (of the module's scans), when its client stops it,
when its client vanishes (the connection closed, or nothing heard for
``[control].client_timeout``: abandoned), or when the daemon stops. ``session_start`` and
``session_end`` events put it in the recording. Its end is sent to its client once every
scan of the window is written to disk, so that the client calibrates exactly the window.

One session at a time: a second ``start`` is refused, naming the one that runs.
"""

from __future__ import annotations

import logging
import os
import selectors
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from loopcal.calibration.parameters import ParameterModel

from ..config.controller import ControllerConfig
from ..events import Level
from ..recorder.engine import Recorder
from ..times import name_stamp, time_text
from .control import (
    MAX_MESSAGE_BYTES,
    ProtocolError,
    StartRequest,
    bind_control_socket,
    encode,
    parse_request,
    peer_of,
)
from .guidance import OFFSETS, Guidance, GuidanceUpdate
from .view import LiveView

log = logging.getLogger(__name__)

#: s after a session ends during which the upkeep still holds its fixes: the session's
#: client calibrates the window and writes the config then
SESSION_GRACE_S = 120.0
#: connections served at once; more are told so and closed
MAX_CONNECTIONS = 16
#: bytes waiting for a slow client beyond which its guidance updates are dropped (its
#: start, end and replies never are)
MAX_OUTGOING_BYTES = 1 << 20
#: protocol errors a connection may make before it is closed
MAX_ERRORS = 20
#: s the end of a session waits for its scans to be written before it is sent unflushed
FLUSH_WAIT_S = 15.0
TICK_S = 0.1  # s between two looks at a running session (its end, its client)
IDLE_S = 1.0


class SessionObserver:
    """The recorder's scans to one session's guidance, and the window they make.

    guidance: the session's :class:`~loopcal.daemon.live.guidance.Guidance`.
    duration_s: the session's length in the module's scans (None: no limit). Rows past it
    are not fed; :attr:`ending` is then ``"duration"``. Once :attr:`closed`, rows are
    ignored: the window is what was fed before.
    """

    name = "session"

    def __init__(self, guidance: Guidance, duration_s: float | None) -> None:
        self.guidance = guidance
        self.duration_s = duration_s
        self.closed = False
        self.ending: str | None = None
        self.scans = 0
        self.first: np.void | None = None
        self.last: np.void | None = None
        self._elapsed_us = 0  # the module's time from the first scan to the last fed
        self._prev: tuple[int, int] | None = None  # (epoch, time64_us) of the last fed

    def feed(self, rows: np.ndarray) -> None:
        if self.closed or not len(rows):
            return
        if self.duration_s is not None:
            rows = self._within_duration(rows)
        if len(rows):
            if self.first is None:
                self.first = rows[0].copy()
            self.last = rows[-1].copy()
            self.scans += len(rows)
            self.guidance.feed(rows)
        if self.ending == "duration":
            self.closed = True

    def _within_duration(self, rows: np.ndarray) -> np.ndarray:
        """The rows less than the duration after the first, in the module's time (its own
        clock; after a restart the new power-on's time goes on from its first scan)."""
        t = rows["time64_us"].astype(np.int64)
        e = rows["epoch"].astype(np.int64)
        epoch0, t0 = self._prev if self._prev is not None else (int(e[0]), int(t[0]))
        prev_t = np.concatenate(([t0], t[:-1]))
        prev_e = np.concatenate(([epoch0], e[:-1]))
        elapsed = self._elapsed_us + np.cumsum(np.where(e == prev_e, t - prev_t, 0))
        n = int(np.searchsorted(elapsed, round(self.duration_s * 1e6)))  # type: ignore[operator]
        if n < len(rows):
            self.ending = "duration"
        if n:
            self._elapsed_us, self._prev = int(elapsed[n - 1]), (int(e[n - 1]), int(t[n - 1]))
        return rows[:n]

    def status(self) -> str:
        return "session: " + self.guidance.status()

    def reload(self, controller: ControllerConfig) -> None:
        self.guidance.reload(controller)

    def window(self) -> dict[str, Any]:
        """The recording's stretch the session covers: ``since_ns``, ``until_ns`` (the
        stamps of its first and last scan, None before any), ``scans``, the first and last
        scans' ``epoch`` and ``counter64``, and ``missed`` (scans lost inside it)."""
        if self.first is None or self.last is None:
            return {"since_ns": None, "until_ns": None, "scans": 0, "missed": 0}
        return {
            "since_ns": int(self.first["stamp_ns"]), "until_ns": int(self.last["stamp_ns"]),
            "scans": self.scans,
            "first": {"epoch": int(self.first["epoch"]),
                      "counter64": int(self.first["counter64"])},
            "last": {"epoch": int(self.last["epoch"]), "counter64": int(self.last["counter64"])},
        }  # fmt: skip


@dataclass(eq=False)
class _Conn:
    """One client connection: what it sent, what waits for it, who it is."""

    sock: socket.socket
    peer: dict[str, Any]
    inbox: bytearray = field(default_factory=bytearray)
    outbox: bytearray = field(default_factory=bytearray)
    errors: int = 0
    closing: bool = False
    heard: float = field(default_factory=time.monotonic)
    dropped: int = 0


@dataclass(eq=False)
class Session:
    """A session: its id, what was asked, by whom, and how it goes."""

    id: str
    request: StartRequest
    asked_by: dict[str, Any]
    observer: SessionObserver
    owner: _Conn | None
    started_ns: int = field(default_factory=time.time_ns)
    followers: list[_Conn] = field(default_factory=list)
    reason: str = ""  # why it ended; "" while it runs
    ended: dict[str, Any] | None = None
    flush_deadline: float = 0.0

    def describe(self) -> dict[str, Any]:
        r = self.request
        out = {"id": self.id, "note": r.note, "asked_by": self.asked_by,
               "started_ns": self.started_ns, "target_mm": r.target_mm,
               "until_enough": r.until_enough, "duration_s": r.duration_s,
               "free": r.free}  # fmt: skip
        if self.reason:
            out["reason"] = self.reason
        return out

    def who(self) -> str:
        a = self.asked_by
        started = time_text(self.started_ns)
        note = f', note "{self.request.note}"' if self.request.note else ""
        return f"session {self.id} of {a.get('user', '?')} (pid {a.get('pid', '?')}), " \
            f"started {started}{note}"  # fmt: skip


class ControlServer:
    """The daemon's control socket, served in a thread of its own (module docstring).

    Parameters
    ----------
    recorder : Recorder
        The running recorder: its analysis thread feeds a session, its events record
        it, its writer's progress says when a session's scans are on disk.
    path : Path
        The control socket (``[control].socket``).
    client_timeout : float
        s of silence from a session's client after which the session is abandoned.
    live : LiveView or None
        The live Foxglove view, which shows a session's guidance too.

    Raises
    ------
    ControlError
        If the socket cannot be listened on (:func:`bind_control_socket`).
    """

    def __init__(self, recorder: Recorder, path: Path, *, client_timeout: float = 30.0,
                 live: LiveView | None = None) -> None:  # fmt: skip
        self.recorder = recorder
        self.path = path
        self.client_timeout = client_timeout
        self.live = live
        self.session: Session | None = None
        #: the last session's words and when it ended (time.monotonic), for the upkeep
        self._last: tuple[str, float] | None = None
        self.sessions_started = 0
        self._requested_end: str | None = None
        self._listener = bind_control_socket(path)
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._listener, selectors.EVENT_READ, None)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._conns: dict[int, _Conn] = {}
        self._lock = threading.Lock()  # outboxes: filled from the analysis thread too
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="loopcal-control", daemon=True)
        self._thread.start()
        log.info("control socket: %s", path)

    # ------------------------------------------------------------------ life

    def session_words(self) -> str:
        """The session under way in words, for the upkeep, which holds its fixes meanwhile
        (the technician's own calibration decides), and for :data:`SESSION_GRACE_S` after
        it ended (its client calibrates and writes then); "" otherwise."""
        s, last = self.session, self._last
        if s is not None:
            return f"a technician's session runs ({s.who()}): its calibration decides"
        if last is not None and time.monotonic() - last[1] < SESSION_GRACE_S:
            return f"a technician's session just ended ({last[0]}): its calibration decides"
        return ""

    def close(self, reason: str = "daemon stopping") -> None:
        """End a running session (``reason``), tell its clients, stop serving, remove the
        socket. Call after the recorder stopped, so that the session's scans are written."""
        self._stop.set()
        self._wake()
        self._thread.join(10.0)
        if self.session is not None:
            if not self.session.reason:
                self._end(reason)
            self._finish(force=True)
        for conn in list(self._conns.values()):
            self._send_now(conn)
            self._drop(conn)
        self._sel.close()
        self._listener.close()
        self._wake_r.close()
        self._wake_w.close()
        try:
            os.unlink(self.path)
        except OSError:
            pass

    def stop_session(self, reason: str = "daemon stopping", timeout: float = 5.0) -> None:
        """End a running session now, from another thread, and wait (up to ``timeout`` s)
        until it has ended: the recorder calls it as it stops, before its last write, so
        that the session's end and every scan of its window reach the recording."""
        self._requested_end = reason
        self._wake()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self._thread.is_alive():
            s = self.session
            if s is None or s.reason:
                return
            time.sleep(0.01)

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except OSError:
            pass  # already awake (the buffer is full) or closing

    def _run(self) -> None:
        while not self._stop.is_set():
            # idle, nothing to watch but the sockets (a request or a wake-up ends the wait)
            wait = TICK_S if self.session is not None or self._requested_end else IDLE_S
            for key, mask in self._sel.select(wait):
                try:
                    self._event(key, mask)
                except Exception:  # noqa: BLE001 - a client never stops the server
                    log.exception("control socket: a request failed")
                    if isinstance(key.data, _Conn):
                        self._drop(key.data)
            try:
                self._tick()
            except Exception:  # noqa: BLE001 - likewise
                log.exception("control socket: the session's bookkeeping failed")

    def _event(self, key: selectors.SelectorKey, mask: int) -> None:
        if key.data is None:
            self._accept()
        elif key.data == "wake":
            try:
                while self._wake_r.recv(4096):
                    pass
            except BlockingIOError:
                pass
            for conn in list(self._conns.values()):
                self._want_write(conn)
        else:
            conn: _Conn = key.data
            if mask & selectors.EVENT_READ:
                self._read(conn)
            if mask & selectors.EVENT_WRITE and conn.sock.fileno() >= 0:
                self._write(conn)

    def _accept(self) -> None:
        try:
            sock, _ = self._listener.accept()
        except (BlockingIOError, OSError):
            return
        sock.setblocking(False)
        conn = _Conn(sock, peer_of(sock))
        if len(self._conns) >= MAX_CONNECTIONS:
            self._reply(conn, {"type": "error", "error": f"too many connections (at most "
                                                          f"{MAX_CONNECTIONS})"})  # fmt: skip
            self._send_now(conn)
            sock.close()
            return
        self._conns[sock.fileno()] = conn
        self._sel.register(sock, selectors.EVENT_READ, conn)

    def _drop(self, conn: _Conn) -> None:
        fd = conn.sock.fileno()
        if fd >= 0:
            try:
                self._sel.unregister(conn.sock)
            except (KeyError, ValueError):
                pass
            self._conns.pop(fd, None)
            conn.sock.close()
        s = self.session
        if s is None:
            return
        if conn in s.followers:
            s.followers.remove(conn)
        if s.owner is conn:
            s.owner = None
            if not s.reason:
                self._end("abandoned", why="its client closed the connection")

    # ------------------------------------------------------------------ i/o

    def _read(self, conn: _Conn) -> None:
        try:
            data = conn.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self._drop(conn)
            return
        conn.heard = time.monotonic()
        if conn.closing:
            return
        conn.inbox += data
        while b"\n" in conn.inbox and not conn.closing:
            line, _, rest = bytes(conn.inbox).partition(b"\n")
            conn.inbox = bytearray(rest)
            self._request(conn, line)
        if len(conn.inbox) > MAX_MESSAGE_BYTES:
            conn.inbox.clear()
            self._refuse(conn, f"a message of more than {MAX_MESSAGE_BYTES} bytes: closing")
            conn.closing = True

    def _reply(self, conn: _Conn, message: dict[str, Any], *, droppable: bool = False) -> None:
        data = encode(message)
        with self._lock:
            if droppable and len(conn.outbox) + len(data) > MAX_OUTGOING_BYTES:
                conn.dropped += 1
                return
            conn.outbox += data

    def _want_write(self, conn: _Conn) -> None:
        if conn.sock.fileno() < 0:
            return
        with self._lock:
            waiting = bool(conn.outbox)
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if waiting else 0)
        try:
            self._sel.modify(conn.sock, events, conn)
        except (KeyError, ValueError):
            pass
        if not waiting and conn.closing:
            self._drop(conn)

    def _write(self, conn: _Conn) -> None:
        with self._lock:
            data = bytes(conn.outbox)
        try:
            sent = conn.sock.send(data)
        except BlockingIOError:
            sent = 0
        except OSError:
            self._drop(conn)
            return
        with self._lock:
            del conn.outbox[:sent]
        self._want_write(conn)

    def _send_now(self, conn: _Conn, timeout: float = 1.0) -> None:
        """Send what waits for ``conn`` before closing it (bounded: a client that reads
        nothing is not waited for)."""
        end = time.monotonic() + timeout
        while conn.outbox and time.monotonic() < end and conn.sock.fileno() >= 0:
            try:
                sent = conn.sock.send(bytes(conn.outbox))
            except BlockingIOError:
                time.sleep(0.01)
                continue
            except OSError:
                return
            del conn.outbox[:sent]

    def _refuse(self, conn: _Conn, text: str) -> None:
        conn.errors += 1
        self._reply(conn, {"type": "error", "error": text})
        if conn.errors >= MAX_ERRORS:
            self._reply(conn, {"type": "error", "error": "too many errors: closing"})
            conn.closing = True
        self._want_write(conn)

    # ------------------------------------------------------------------ requests

    def _request(self, conn: _Conn, line: bytes) -> None:
        try:
            name, start = parse_request(line)
        except ProtocolError as exc:
            self._refuse(conn, str(exc))
            return
        s = self.session
        if name == "status":
            self._reply(conn, {"type": "status", "session": s.describe() if s else None,
                               "recorder": self.recorder.status_line()})  # fmt: skip
        elif name == "start":
            assert start is not None
            self._start(conn, start)
        elif name == "stream":
            if s is None or s.reason:
                self._refuse(conn, "no session runs")
                return
            if conn not in s.followers:
                s.followers.append(conn)
            self._reply(conn, {"type": "streaming", "session": s.describe()})
        elif name == "stop":
            if s is None or s.reason:
                self._refuse(conn, "no session runs")
                return
            if s.owner is not conn:
                self._refuse(conn, f"only the client that started it can stop {s.who()}")
                return
            self._end("stopped")
        self._want_write(conn)

    def _start(self, conn: _Conn, req: StartRequest) -> None:
        s = self.session
        if s is not None:
            what = "is ending" if s.reason else "runs"
            self._refuse(conn, f"a session {what}: {s.who()}; one session at a time")
            return
        controller = self.recorder.controller
        try:
            model = ParameterModel.parse(req.free, ()) if req.free else controller.model()
        except ValueError as exc:
            self._refuse(conn, f"start: free: {exc}")
            return
        self.sessions_started += 1
        sid = name_stamp() + f"-{self.sessions_started}"
        holder: dict[str, Session] = {}

        def update(u: GuidanceUpdate) -> None:
            session = holder["s"]
            for c in [session.owner, *session.followers]:
                if c is not None:
                    self._reply(c, {"type": "guidance", "update": u.as_json(),
                                    "lines": u.render()}, droppable=True)  # fmt: skip
            self._wake()
            if self.live is not None:
                self.live.guidance(u)

        def enough(u: GuidanceUpdate) -> None:
            if req.until_enough:
                holder["s"].observer.ending = "enough"
                holder["s"].observer.closed = True
                self._wake()

        guidance = Guidance(controller, model, target_mm=req.target_mm, on_update=update,
                            on_enough=enough)  # fmt: skip
        session = Session(sid, req, conn.peer, SessionObserver(guidance, req.duration_s), conn)
        holder["s"] = session
        self.session = session
        # the reply first: once the analysis has the observer, its thread may send the
        # client a guidance update, which must not reach it before it knows it started
        self._reply(conn, {"type": "started", "session": session.describe()})
        self.recorder.analysis.add(session.observer)
        note = f': "{req.note}"' if req.note else ""
        self.recorder.emit(
            "session_start", Level.INFO,
            f"session {sid} started by {conn.peer.get('user', '?')} (pid "
            f"{conn.peer.get('pid', '?')}){note}",
            session=sid, note=req.note, asked_by=conn.peer, target_mm=req.target_mm,
            until_enough=req.until_enough, duration_s=req.duration_s, free=req.free,
        )  # fmt: skip

    # ------------------------------------------------------------------ the session's end

    def _tick(self) -> None:
        self._reap_idle()
        s = self.session
        if s is None:
            return
        if not s.reason:
            if self._requested_end is not None:
                self._end(self._requested_end)
            elif s.observer.ending is not None:
                self._end(s.observer.ending)
            elif s.owner is not None and time.monotonic() - s.owner.heard > self.client_timeout:
                self._end("abandoned", why=f"nothing heard from its client for "
                                           f"{self.client_timeout:g} s")  # fmt: skip
        if s.reason:
            self._finish()

    def _reap_idle(self) -> None:
        """Close connections that neither own nor follow a session and have said nothing
        for the client timeout: idle ones would hold the places of those that come to work."""
        s = self.session
        busy = () if s is None else (s.owner, *s.followers)
        limit = time.monotonic() - self.client_timeout
        for conn in list(self._conns.values()):
            if conn.heard < limit and conn not in busy:
                self._drop(conn)

    def _end(self, reason: str, why: str = "") -> None:
        """End the session: no more scans for it, its window fixed, ``session_end``."""
        s = self.session
        assert s is not None and not s.reason
        s.observer.closed = True
        self.recorder.analysis.remove(s.observer)  # no feed of it under way after this
        s.reason = reason
        window = s.observer.window()
        last = s.observer.guidance.last
        enough = bool(last is not None and last.enough)
        std = {} if last is None else {n: v for n, v in last.std.items() if np.isfinite(v)}
        worst = max((std[n] for n in OFFSETS if n in std), default=None)
        text = f"session {s.id} ended ({reason}{': ' + why if why else ''}): " \
            f"{window['scans']:,} scans" + (
                f", every offset within {worst:.3f} mm" if worst is not None else "") + (
                ", enough to calibrate" if enough else "")  # fmt: skip
        level = Level.WARNING if reason == "abandoned" else Level.INFO
        self.recorder.emit("session_end", level, text, session=s.id, reason=reason, why=why,
                           enough=enough, std=std, **window)  # fmt: skip
        s.ended = {**s.describe(), "reason": reason, "why": why, "enough": enough,
                   "std": std, **window}  # fmt: skip
        s.flush_deadline = time.monotonic() + FLUSH_WAIT_S

    def _finish(self, *, force: bool = False) -> None:
        """Send the end once the window's scans are on disk (or the wait is over)."""
        s = self.session
        assert s is not None and s.ended is not None
        until = s.ended.get("until_ns")
        status = self.recorder.status
        written = status.written_through_ns
        flushed = until is None or (written is not None and written >= until)
        if not flushed and not force and time.monotonic() < s.flush_deadline:
            return
        message = {**s.ended, "flushed": flushed}
        if not flushed:
            message["flush_error"] = status.disk_error or (
                "the window's last scans were not written in time")  # fmt: skip
        for c in [s.owner, *s.followers]:
            if c is not None:
                self._reply(c, {"type": "ended", "session": message})
                self._want_write(c)
        self._last = (s.who(), time.monotonic())
        self.session = None

"""An LDQ-412 written from the datasheet alone, independently of simulator/: the tests'
"module we did not build". It shares no code with the emulator (not even loopcal.drivers.ldq412)
and makes other choices wherever the datasheet leaves room:

- its own scanning thread on its own clock: ``ppm`` fast against the host (default +150),
  scan 0 taken ``phase_us`` after power-on (default 1809 µs), silent until then; the
  thread sleeps until a scan is due, and a request takes the scans due first (no thread
  polls: a busy machine runs them late, and four of these polling every 0.5 ms, beside two
  CPU hogs, left a module silent through 20 connects of 0.1 s);
- its FIFO answers only the scans that wait (no filler scans: a shorter answer), and it
  takes at most 64 registers per read (exception 03 beyond: a 20-scan FIFO read is 120);
- every answer 1 to 4 ms late; a power cycle closes its TCP sockets at once;
- Modbus TCP framed by hand on a plain socket, Modbus RTU and ASCII on a pseudo-terminal
  pair (the driver opens the other end like /dev/ttyUSB0), each served by a thread.

It keeps every scan it made in :attr:`IndependentModule.made` ((boot, counter, time_us,
codes, status) tuples). Not thread-safe beyond what its own lock guards; for tests only.
"""

from __future__ import annotations

import math
import os
import random
import select
import socket
import struct
import threading
import time
import tty

MAX_REGS = 64
FIFO_DEPTH = 256


def crc16(data: bytes) -> int:
    """Modbus RTU CRC (polynomial 0xA001, initial 0xFFFF)."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


class IndependentModule:
    """Start with :meth:`start`; ``url`` is what a driver opens."""

    def __init__(
        self, transport: str, *, rate_hz: int = 20, ppm: float = 150.0, phase_us: int = 1809
    ) -> None:
        self.transport = transport
        self.rate_hz = rate_hz
        self.ppm = ppm
        self.phase_us = phase_us
        self.made: list[tuple[int, int, int, tuple[int, int, int, int], int]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._rng = random.Random(13)
        self._boot = -1
        self._power_on()
        self.url = ""

    # ------------------------------------------------------------------ the module

    def _power_on(self) -> None:
        self._boot += 1
        self._on_at = time.monotonic()
        self._dark_until = 0.0
        self._rate = self.rate_hz
        self._checksum = False
        self._next = 0  # counter of the next scan
        self._latest: tuple[int, int, tuple[int, int, int, int], int] | None = None
        self._fifo: list[tuple[int, tuple[int, int, int, int]]] = []
        self._overflow = False
        self._restart = True

    def _device_us(self, now: float) -> int:
        return int((now - self._on_at) * 1e6 * (1 + self.ppm * 1e-6))

    def _catch_up(self) -> float:
        """Take every scan due by now (holding the lock); the wall time to look again, s.

        Called by the scanning thread when a scan is due and by every request before it is
        answered: the answers are the module's whenever a loaded machine runs the thread.
        """
        now = time.monotonic()
        if now < self._dark_until:
            return self._dark_until - now
        if self._dark_until:
            self._power_on()
        period_us = 1_000_000 // self._rate
        due_us = self._device_us(now)
        while self.phase_us + self._next * period_us <= due_us:
            self._take(self.phase_us + self._next * period_us)
        ahead_us = self.phase_us + self._next * period_us - due_us
        return ahead_us / 1e6 / (1 + self.ppm * 1e-6)

    def _scan_loop(self) -> None:
        wait = 0.0
        while not self._stop.wait(min(wait, 0.05)):  # 0.05: a rate written meanwhile
            with self._lock:
                wait = self._catch_up()

    def _take(self, t_us: int) -> None:
        c = self._next
        codes = tuple(
            int(2048 + 1500 * math.sin(0.37 * (ch + 1) * t_us / 1e6 + ch)) for ch in range(4)
        )
        status = sum(1 << ch for ch, v in enumerate(codes) if v in (0, 4095))
        status |= (0x100 if self._overflow else 0) | (0x200 if self._restart else 0)
        if len(self._fifo) == FIFO_DEPTH:
            self._fifo.pop(0)
            self._overflow = True
        self._fifo.append((c & 0xFFFFFFFF, codes))
        self._latest = (c & 0xFFFFFFFF, t_us & 0xFFFFFFFF, codes, status & 0xFF)
        self.made.append((self._boot, c, t_us & 0xFFFFFFFF, codes, status))
        self._next += 1

    def power_cycle(self, off_s: float = 1.75) -> None:
        with self._lock:
            self._dark_until = time.monotonic() + off_s
            self._latest = None
        if self.transport == "modbus-tcp":
            self._drop_connections()

    def _ready(self) -> bool:
        """Whether it answers (holding the lock): powered, and past its scan 0."""
        self._catch_up()
        return self._latest is not None and time.monotonic() >= self._dark_until

    def _status(self) -> int:
        assert self._latest is not None
        return self._latest[3] | (0x100 if self._overflow else 0) | (0x200 if self._restart else 0)

    # ------------------------------------------------------------------ Modbus PDUs

    def _pdu(self, req: bytes) -> bytes | None:
        """A Modbus request PDU -> the answer PDU (None: no answer)."""
        with self._lock:
            if not self._ready() or len(req) < 5:
                return None
            fc = req[0]
            if fc in (3, 4):
                addr, count = struct.unpack(">HH", req[1:5])
                if not 1 <= count <= MAX_REGS:
                    return bytes([fc | 0x80, 3])
                regs = self._input(addr, count) if fc == 4 else self._holding(addr, count)
                if isinstance(regs, int):
                    return bytes([fc | 0x80, regs])
                return bytes([fc, 2 * len(regs)]) + struct.pack(f">{len(regs)}H", *regs)
            if fc == 6:
                addr, value = struct.unpack(">HH", req[1:5])
                err = self._write(addr, value)
                return bytes([fc | 0x80, err]) if err else req[:5]
            return bytes([fc | 0x80, 1])

    def _input(self, addr: int, count: int) -> list[int] | int:
        if addr == 0 and count <= 10:
            c, t, codes, _ = self._latest  # type: ignore[misc]
            regs = [c >> 16, c & 0xFFFF, t >> 16, t & 0xFFFF, *codes, self._status(),
                    len(self._fifo)]  # fmt: skip
            return regs[:count]
        if addr == 512 and count <= 4:
            return [0x0412, 0x0307, 0, 12345][:count]
        if addr == 256 and count % 6 == 0 and count <= 120:
            out: list[int] = []
            for _ in range(count // 6):
                if not self._fifo:
                    break  # only the waiting scans: a short answer
                c, codes = self._fifo.pop(0)
                out += [c >> 16, c & 0xFFFF, *codes]
            return out
        return 2

    def _holding(self, addr: int, count: int) -> list[int] | int:
        regs = [self._rate, 1, 0, 0, int(self._checksum)]
        return regs[addr : addr + count] if addr + count <= 5 else 2

    def _write(self, addr: int, value: int) -> int:
        if addr == 0 and 1 <= value <= 200:
            self._rate = value  # (a rate change re-phases nothing here: tests keep it)
        elif addr == 2 and value in (0, 1):
            if value:
                self._fifo.clear()
                self._overflow = False
        elif addr == 3 and value in (0, 1):
            self._restart = self._restart and not value
        elif addr == 4 and value in (0, 1):
            self._checksum = bool(value)
        elif addr in (1,) and value in (1, 2, 4, 8, 16):
            pass
        else:
            return 3 if addr <= 4 else 2
        return 0

    def _late(self) -> None:
        time.sleep(self._rng.uniform(0.001, 0.004))

    # ------------------------------------------------------------------ Modbus TCP

    def _tcp_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except OSError:
                continue
            self._conns.append(conn)
            t = threading.Thread(target=self._tcp_session, args=(conn,), daemon=True)
            t.start()

    def _tcp_session(self, conn: socket.socket) -> None:
        buf = b""
        boot = self._boot
        with conn:
            while not self._stop.is_set():
                try:
                    data = conn.recv(512)
                except OSError:
                    return
                with self._lock:
                    rebooted = self._boot != boot and self._ready()
                if not data or rebooted:
                    return  # a rebooted module knows nothing of this connection
                buf += data
                while len(buf) >= 7 and len(buf) >= 6 + struct.unpack(">H", buf[4:6])[0]:
                    n = 6 + struct.unpack(">H", buf[4:6])[0]
                    frame, buf = buf[:n], buf[n:]
                    tid, proto, _, unit = struct.unpack(">HHHB", frame[:7])
                    answer = self._pdu(frame[7:]) if proto == 0 and unit == 1 else None
                    if answer is None:
                        continue
                    self._late()
                    head = struct.pack(">HHHB", tid, 0, len(answer) + 1, unit)
                    try:
                        conn.sendall(head + answer)
                    except OSError:
                        return

    def _drop_connections(self) -> None:
        for c in self._conns:
            try:
                c.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        self._conns = []

    # ------------------------------------------------------------------ serial lines

    def _serial_loop(self) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                if not select.select([self._fd], [], [], 0.05)[0]:
                    continue
                data = os.read(self._fd, 256)
            except BlockingIOError:
                continue
            except (OSError, ValueError):
                return
            buf += data
            if self.transport == "ascii":
                while b"\r" in buf:
                    frame, buf = buf.split(b"\r", 1)
                    self._answer(self._ascii(frame))
            else:
                buf = self._rtu(buf)

    def _answer(self, out: bytes | None) -> None:
        if out is None:
            return
        self._late()
        # the whole answer, as a UART sends it: the master is non-blocking, and a write
        # while the pty's buffer is full takes part of it or nothing (ignored, that would
        # cut an answer short: no CR, a "partial answer" to the driver)
        view = memoryview(out)
        deadline = time.monotonic() + 2.0
        while view and time.monotonic() < deadline and not self._stop.is_set():
            try:
                view = view[os.write(self._fd, view) :]
            except BlockingIOError:
                select.select([], [self._fd], [], 0.05)
            except OSError:
                return

    def _rtu(self, buf: bytes) -> bytes:
        """Answer every whole request in ``buf`` (all ours are 8 bytes); the rest back."""
        while len(buf) >= 8:
            frame, buf = buf[:8], buf[8:]
            if crc16(frame[:6]) != struct.unpack("<H", frame[6:8])[0]:
                return b""  # line noise: drop what we have
            if frame[0] != 1:
                continue
            answer = self._pdu(frame[1:6])
            if answer is not None:
                body = bytes([1]) + answer
                self._answer(body + struct.pack("<H", crc16(body)))
        return buf

    def _ascii(self, frame: bytes) -> bytes | None:
        with self._lock:
            if not self._ready():
                return None
            if self._checksum:
                frame, cs = frame[:-2], frame[-2:]
                if cs != b"%02X" % (sum(frame) & 0xFF):
                    return None
            if len(frame) < 3 or frame[1:3] != b"01" or frame[:1] not in b"#$%":
                return None
            cmd = frame[:1] + frame[3:]
            if cmd == b"#":
                c, t, codes, _ = self._latest  # type: ignore[misc]
                body = b">%08X%08X" % (c, t) + b"".join(b"%03X" % v for v in codes)
                body += b"%04X" % self._status()
            elif cmd == b"$M":
                body = b"!01LDQ412"
            elif cmd == b"$F":
                body = b"!013.07"
            elif cmd == b"$R":
                body = b"!01%04X" % self._rate
            else:
                body = b"?01"
            if self._checksum:
                body += b"%02X" % (sum(body) & 0xFF)
            return body + b"\r"

    # ------------------------------------------------------------------ life

    def start(self) -> IndependentModule:
        self._conns: list[socket.socket] = []
        loops = [self._scan_loop]
        if self.transport == "modbus-tcp":
            self._server = socket.create_server(("127.0.0.1", 0))
            self._server.settimeout(0.05)
            self.url = f"modbus-tcp://127.0.0.1:{self._server.getsockname()[1]}?unit=1"
            loops.append(self._tcp_loop)
        else:
            self._fd, slave = os.openpty()
            tty.setraw(slave)
            os.set_blocking(self._fd, False)
            self._slave = slave
            path = os.ttyname(slave)
            self.url = (
                f"ascii://{path}?addr=01" if self.transport == "ascii" else f"modbus-rtu://{path}"
            )
            loops.append(self._serial_loop)
        for loop in loops:
            t = threading.Thread(target=loop, daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(2)
        if self.transport == "modbus-tcp":
            self._server.close()
            self._drop_connections()
        else:
            for fd in (self._fd, self._slave):
                try:
                    os.close(fd)
                except OSError:
                    pass

    def __enter__(self) -> IndependentModule:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

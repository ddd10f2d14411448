"""Another Modbus master on the module: a plain pymodbus client, not loopcal's driver, that
reads the FIFO window as a SCADA poll or a second host would, and remembers every scan it
took (the truth a test compares loopcal's gaps with)."""

from __future__ import annotations

from pymodbus.client import ModbusTcpClient

FIFO_WINDOW = 256  # input register of the FIFO window (the datasheet's)
SCAN_REGS = 6  # counter hi, counter lo, ch1..ch4
FILLER = 0xFFFF
LEVEL_REGISTER = 9


class ForeignReader:
    """A Modbus TCP client of the module at ``host:port`` that reads its FIFO window.

    ``counters``: the raw counters of every scan it took, in order. A failed read raises
    (a test cannot know what an unanswered FIFO read took).
    """

    def __init__(self, host: str, port: int, *, unit: int = 1, timeout: float = 3.0) -> None:
        self.unit = unit
        self.counters: list[int] = []
        self._client = ModbusTcpClient(host, port=port, timeout=timeout, retries=0)
        if not self._client.connect():
            raise ConnectionError(f"cannot connect to {host}:{port}")

    def _read(self, address: int, count: int) -> list[int]:
        rsp = self._client.read_input_registers(address, count=count, device_id=self.unit)
        if rsp.isError():
            raise RuntimeError(f"read {address}+{count}: {rsp}")
        return list(rsp.registers)

    def level(self) -> int:
        """The module's FIFO level (input register 9); takes nothing."""
        return self._read(LEVEL_REGISTER, 1)[0]

    def take(self, n: int = 20) -> list[int]:
        """Read ``n`` scans' worth of the FIFO window (1..20): the counters it took."""
        regs = self._read(FIFO_WINDOW, n * SCAN_REGS)
        got = []
        for i in range(0, len(regs), SCAN_REGS):
            scan = regs[i : i + SCAN_REGS]
            if all(r == FILLER for r in scan):
                break
            got.append(scan[0] << 16 | scan[1])
        self.counters += got
        return got

    def close(self) -> None:
        self._client.close()

    def __enter__(self) -> ForeignReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""What loopcal's tests and bench scripts share: real recordings, real subprocesses, the
emulated module in this process, damaged inputs, the tools users check files with.

Nothing here is a mock: every helper drives the real code (the daemon's writer and
reader, the emulator on a real socket, ``loopcal`` as a subprocess). It is imported as
``tests.support`` from the repository's root (pytest puts it on ``sys.path``; bench
scripts run as ``python -m bench.NAME``); it is not part of the installed package.

- :mod:`.rows`: scan rows as the recorder makes them (one builder), ``T0``;
- :mod:`.recordings`: recordings written by the daemon's writer, directories, compacted
  copies;
- :mod:`.mutations`: damage (bit flips, tears, swapped chunks, ...) and its verdict;
- :mod:`.sessions`: technician sessions, recorded live or written from offline scans;
- :mod:`.processes`: ``loopcal`` subprocesses, metrics, ports, the notify socket;
- :mod:`.emulator`: the emulated module in this process and its truth;
- :mod:`.foreign`: another Modbus master reading the module's FIFO (plain pymodbus);
- :mod:`.replay`: replay round trips;
- :mod:`.timeline`: a module's scan timeline in simulated time (polls, stamps);
- :mod:`.independent_module`: a module written from the datasheet alone;
- :mod:`.js`: Node.js tools (Foxglove's MCAP reader, Chromium).
"""

from pathlib import Path

#: the repository's root
ROOT = Path(__file__).resolve().parent.parent.parent

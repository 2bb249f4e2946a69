"""The simulated real board (``--board ulx3s-sim``): the board's top level at its UART pins under
Verilator, reached through the same framed link as the real board.

:class:`UartSimTransport` is a :class:`~blockray.host_driver.board.framed.FramedTransport` whose raw
byte pipe is a virtual serial port that drives the simulated ``rx`` pin and decodes ``tx``, and
whose reset is a break on ``rx``: by default :class:`NativeUartPipe`, the top and the bridge in
one C++ loop (sim/native/uart_harness.cpp, called with whole buffers); or, with ``native=False``,
:class:`UartSimPipe`, a localhost socket to a cocotb test (sim/uart_cocotb.py) clocked from
Python. Both bridges run the same clock cycles (tests/test_native_uart.py). ``faults`` injects faults on it (``--link-faults``). The simulation is
:class:`blockray.rtl.link.SerialLink` around the core, as on the ULX3S (:mod:`blockray.rtl.ulx3s`
adds only the PLL, the reset synchroniser and the pins), with a short bit time (``divisor``,
4 clock cycles by default, where the board runs 15 at 3 Mbaud). Built once per design with
:func:`blockray.sim.cocotb_support.build_verilator` (cached).

    link = UartSimTransport(EchoCore())      # or the board core
    link.send(b"...")
    link.recv(3)
"""

import math
import socket
import tempfile
import weakref
from pathlib import Path

from .framed import FaultyPipe, FramedTransport
from .transport import TransportError

__all__ = ["UartSimPipe", "NativeUartPipe", "UartSimTransport", "SIM_DIVISOR"]

#: clock cycles per bit in simulation (the UART's minimum)
SIM_DIVISOR = 4
_MODULE_DIR = Path(__file__).resolve().parents[2] / "sim"


class _SerialPort:
    """What both bridges share: time-outs counted in simulated clock cycles and the break.
    A subclass sets ``divisor``, ``cycles``, ``queued`` and gives ``write``, ``run`` and ``_break``."""

    #: simulated seconds per clock cycle (sim/uart_cocotb.py's clock)
    CYCLE_SECONDS = 10e-9
    #: the break's length and the quiet time after it, in bit times (a break is 10 low bits or more)
    BREAK_BITS, AFTER_BREAK_BITS = 20, 40

    def clock(self):
        """Simulated seconds run so far (the framed link's clock)."""
        return self.cycles * self.CYCLE_SECONDS

    def read(self, timeout):
        # the silence counts from when what was written has left (10 bits a byte)
        return self.run(math.ceil(timeout / self.CYCLE_SECONDS) + 10 * self.divisor * self.queued)

    def reset(self):
        self._break(True)
        self._quiet(self.BREAK_BITS)
        self._break(False)
        self._quiet(self.AFTER_BREAK_BITS)

    def _quiet(self, bits):
        """Run ``bits`` bit times whatever arrives, and drop it."""
        end = self.cycles + bits * self.divisor
        while self.cycles < end:
            self.run(end - self.cycles)


class NativeUartPipe(_SerialPort):
    """``core`` behind :class:`~blockray.rtl.link.SerialLink` in the native UART harness, as a byte
    pipe in lockstep with the host (the contract of :class:`UartSimPipe`). ``name``: the cache
    entry of its build; ``source``: as :func:`~blockray.sim.native.build_native`'s."""

    def __init__(self, core, *, divisor=SIM_DIVISOR, fifo_depth=2048, name="blockray_uart_sim", source=None):
        from ...rtl.link import SerialLink
        from ...sim.native import UartPorts, build_native
        from ...sim.native.uart import NativeUart
        self.divisor, self.cycles, self.queued = divisor, 0, 0
        build = build_native(lambda: SerialLink(core, divisor=divisor, fifo_depth=fifo_depth), name=name,
                             ports=UartPorts(), source=source)
        self.log_path = build.build_dir / "build.log"
        self._uart = NativeUart(build, divisor)

    def write(self, data):
        self._uart.write(data)
        self.queued += len(data)

    def run(self, cycles):
        """Run for at most ``cycles`` clock cycles, less if a frame delimiter came first; the bytes
        received meanwhile."""
        out, ran, self.queued = self._uart.run(max(1, int(cycles)))
        self.cycles += ran
        return out

    def _break(self, on):
        self._uart.brk(on)

    def close(self):
        self._uart.close()


class UartSimPipe(_SerialPort):
    """``core`` (a component with ``i_bytes``/``o_bytes``) behind :class:`~blockray.rtl.link.SerialLink`
    under Verilator, as a byte pipe in lockstep with the host: the simulation runs only within
    :meth:`read`, for at most its ``timeout`` in simulated seconds after the bytes written have
    left on ``rx`` (``clock()``: the simulated seconds run so far), so every time-out counts clock
    cycles of silence and a run does not depend on the machine's load. ``divisor``, ``fifo_depth``: the link's; ``name``: the Verilog top module
    (and cache entry); ``answer_seconds``: wall-clock seconds the simulator may take to answer
    one run before it is taken for dead. ``reset()``: a break on ``rx`` of ``BREAK_BITS`` bit
    times, then what came before is dropped."""

    def __init__(self, core, *, divisor=SIM_DIVISOR, fifo_depth=2048, name="blockray_uart_sim", startup_timeout=600,
                 answer_seconds=600):
        from ...rtl.link import SerialLink
        from ...sim.cocotb_support import build_verilator, start_cocotb, stop_cocotb

        self.divisor, self.answer_seconds = divisor, answer_seconds
        self.cycles = 0
        self.queued = 0             # bytes written and not yet sent on rx
        self.build = build_verilator(SerialLink(core, divisor=divisor, fifo_depth=fifo_depth), name=name)
        self.workdir = Path(tempfile.mkdtemp(prefix="blockray_uart_"))
        self.log_path = self.workdir / "simulator.log"
        self._log = open(self.log_path, "w")
        try:
            self._proc, self._sock = start_cocotb(
                self.build, "uart_cocotb", module_dir=_MODULE_DIR, workdir=self.workdir, log=self._log,
                port_env="BLOCKRAY_UART_PORT", env={"BLOCKRAY_UART_DIVISOR": str(divisor)},
                startup_timeout=startup_timeout, error=TransportError)
        except BaseException:
            self._log.close()
            raise
        self._finalizer = weakref.finalize(self, stop_cocotb, self._proc, self._sock)
        self._pending = bytearray()

    def _message(self, kind, payload=b""):
        try:
            self._sock.sendall(kind + len(payload).to_bytes(2, "little") + payload)
        except OSError as e:
            raise TransportError(f"the UART simulation ended ({e}); see {self.log_path}") from None

    def _take(self, n):
        while len(self._pending) < n:
            try:
                data = self._sock.recv(65536)
            except socket.timeout:
                raise TransportError(f"the UART simulation did not answer in {self.answer_seconds:g} s; "
                                     f"see {self.log_path}") from None
            except OSError as e:
                raise TransportError(f"the UART simulation ended ({e}); see {self.log_path}") from None
            if not data:
                raise TransportError(f"the UART simulation ended; see {self.log_path}")
            self._pending += data
        out = bytes(self._pending[:n])
        del self._pending[:n]
        return out

    def write(self, data):
        for i in range(0, len(data), 0xFFFF):
            self._message(b"D", data[i:i + 0xFFFF])
        self.queued += len(data)

    def run(self, cycles):
        """Run the simulation for at most ``cycles`` clock cycles, less if a frame delimiter came
        first; the bytes received meanwhile."""
        self._message(b"R", max(1, int(cycles)).to_bytes(4, "little"))
        self._sock.settimeout(self.answer_seconds)
        header = self._take(13)
        if header[:1] != b"T":
            raise TransportError(f"the UART simulation answered {header[:1]!r}, not a run; see {self.log_path}")
        self.cycles += int.from_bytes(header[1:5], "little")
        self.queued = int.from_bytes(header[5:9], "little")
        return self._take(int.from_bytes(header[9:13], "little"))

    def _break(self, on):
        self._message(b"B" if on else b"b")

    def close(self):
        if getattr(self, "_sock", None) is None:
            return
        try:
            self._message(b"Q")
        except TransportError:
            pass
        self._finalizer()
        self._sock = None
        self._log.close()


class UartSimTransport(FramedTransport):
    """The framed link to ``core`` over :class:`NativeUartPipe` (``native=False``:
    :class:`UartSimPipe`; ``divisor``, ``fifo_depth``, ``name``: its), reset once opened. ``faults``: a
    :class:`~blockray.host_driver.board.framed.LinkFaults` to inject (``board``: which board's seeds).
    The time-outs are in simulated seconds (``timeout``: silence before a resend, 0.5 ms: 5 of the
    host's frames at the simulated bit time), so which faults need one, and how many there are,
    depends only on the faults injected."""

    def __init__(self, core, *, divisor=SIM_DIVISOR, fifo_depth=2048, name="blockray_uart_sim", faults=None, board=0,
                 startup_timeout=600, timeout=5e-4, max_retries=12, answer_timeout=6e-3, native=True, source=None):
        if native:
            pipe = NativeUartPipe(core, divisor=divisor, fifo_depth=fifo_depth, name=name + "_native", source=source)
        else:
            pipe = UartSimPipe(core, divisor=divisor, fifo_depth=fifo_depth, name=name, startup_timeout=startup_timeout)
        self.log_path = pipe.log_path
        if faults is not None:
            pipe = FaultyPipe(pipe, faults.injector(board, 0), faults.injector(board, 1))
        super().__init__(pipe, where=f"the simulated board {board}", timeout=timeout, max_retries=max_retries,
                         answer_timeout=answer_timeout)
        try:
            self.reset()
        except BaseException:
            self.close()
            raise

"""The simulated real board (``--board ulx3s-sim``): the board's top level at its UART pins under
Verilator, reached through the same framed link as the real board.

:class:`UartSimTransport` is a :class:`~blockray.host_driver.board.framed.FramedTransport` whose raw
byte pipe (:class:`UartSimPipe`) is a localhost socket to a cocotb test (sim/uart_cocotb.py)
that drives the simulated ``rx`` pin and decodes ``tx``: a virtual serial port, whose reset is a
break on ``rx``. ``faults`` injects faults on it (``--link-faults``). The simulation is
:class:`blockray.rtl.link.SerialLink` around the core, as on the ULX3S (:mod:`blockray.rtl.ulx3s`
adds only the PLL, the reset synchroniser and the pins), with a short bit time (``divisor``,
4 clock cycles by default, where the board runs 15 at 3 Mbaud). Built once per design with
:func:`blockray.sim.cocotb_support.build_verilator` (cached).

    link = UartSimTransport(EchoCore())      # or the board core
    link.send(b"...")
    link.recv(3)
"""

import socket
import tempfile
import weakref
from pathlib import Path

import time

from .framed import FaultyPipe, FramedTransport
from .transport import TransportError

__all__ = ["UartSimPipe", "UartSimTransport", "SIM_DIVISOR"]

#: clock cycles per bit in simulation (the UART's minimum)
SIM_DIVISOR = 4
_MODULE_DIR = Path(__file__).resolve().parents[2] / "sim"


class UartSimPipe:
    """``core`` (a component with ``i_bytes``/``o_bytes``) behind :class:`~blockray.rtl.link.SerialLink`
    under Verilator, as a byte pipe; ``divisor``, ``fifo_depth``: the link's; ``name``: the
    Verilog top module (and cache entry). ``reset()``: a break on ``rx``, then what came before
    is dropped."""

    def __init__(self, core, *, divisor=SIM_DIVISOR, fifo_depth=2048, name="blockray_uart_sim", startup_timeout=600,
                 break_seconds=0.05):
        from ...rtl.link import SerialLink
        from ...sim.cocotb_support import build_verilator, start_cocotb, stop_cocotb

        self.break_seconds = break_seconds
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

    def _message(self, kind, payload=b""):
        try:
            self._sock.sendall(kind + len(payload).to_bytes(2, "little") + payload)
        except OSError as e:
            raise TransportError(f"the UART simulation ended ({e}); see {self.log_path}") from None

    def write(self, data):
        for i in range(0, len(data), 0xFFFF):
            self._message(b"D", data[i:i + 0xFFFF])

    def read(self, timeout):
        self._sock.settimeout(timeout)
        try:
            data = self._sock.recv(65536)
        except (socket.timeout, BlockingIOError):
            return b""
        if not data:
            raise TransportError(f"the UART simulation ended; see {self.log_path}")
        return data

    def reset(self):
        self._message(b"B")
        time.sleep(self.break_seconds)
        while self.read(0.01):
            pass
        self._message(b"b")

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
    """The framed link to ``core`` over :class:`UartSimPipe` (``divisor``, ``fifo_depth``,
    ``name``: its), reset once opened. ``faults``: a
    :class:`~blockray.host_driver.board.framed.LinkFaults` to inject (``board``: which board's seeds).
    The time-outs are the simulation's: a bit lasts ``divisor`` cycles of a simulator far slower
    than a board (``timeout``: silence before a resend)."""

    def __init__(self, core, *, divisor=SIM_DIVISOR, fifo_depth=2048, name="blockray_uart_sim", faults=None, board=0,
                 startup_timeout=600, timeout=10.0, max_retries=12, answer_timeout=60.0):
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

"""The simulated real board (``--board ulx3s-sim``): the board's top level at its UART pins under
Verilator, reached through the same link protocol as the real board.

:class:`UartSimTransport` is a :class:`~blockray.host_driver.serial_link.CreditedLink` whose raw
byte pipe is a localhost socket to a cocotb test (sim/uart_cocotb.py) that drives the simulated
``rx`` pin and decodes ``tx``: a virtual serial port. The simulation is
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

from .serial_link import CreditedLink
from .transport import TransportError

__all__ = ["UartSimTransport", "SIM_DIVISOR"]

#: clock cycles per bit in simulation (the UART's minimum)
SIM_DIVISOR = 4
_MODULE_DIR = Path(__file__).resolve().parent.parent / "sim"


class UartSimTransport(CreditedLink):
    """``core`` (a component with ``i_bytes``/``o_bytes``) behind the UART link under Verilator.
    ``divisor``, ``fifo_depth``, ``result_depth``: :class:`~blockray.rtl.link.SerialLink`'s;
    ``name``: the Verilog top module (and cache entry)."""

    where = "the simulated board"

    def __init__(self, core, *, divisor=SIM_DIVISOR, fifo_depth=2048, result_depth=512, name="blockray_uart_sim",
                 startup_timeout=600, timeout=120.0, answer_timeout=60.0):
        from ..rtl.link import SerialLink
        from ..sim.cocotb_support import build_verilator, start_cocotb, stop_cocotb

        super().__init__(timeout=timeout, answer_timeout=answer_timeout, break_seconds=0.05)
        top = SerialLink(core, divisor=divisor, fifo_depth=fifo_depth, result_depth=result_depth)
        self.build = build_verilator(top, name=name)
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
        try:
            self.reset()
        except BaseException:
            self.close()
            raise

    def _message(self, kind, payload=b""):
        try:
            self._sock.sendall(kind + len(payload).to_bytes(2, "little") + payload)
        except OSError as e:
            raise TransportError(f"the UART simulation ended ({e}); see {self.log_path}") from None

    def _write(self, data):
        for i in range(0, len(data), 0xFFFF):
            self._message(b"D", data[i:i + 0xFFFF])

    def _read(self, timeout):
        self._sock.settimeout(timeout)
        try:
            data = self._sock.recv(65536)
        except (socket.timeout, BlockingIOError):
            return b""
        if not data:
            raise TransportError(f"the UART simulation ended; see {self.log_path}")
        return data

    def _set_break(self, on):
        self._message(b"B" if on else b"b")

    def _drop_input(self):
        while self._read(0.01):
            pass

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

"""The simulated real board (``--board ulx3s-sim``): the board's top level at its UART pins under
Verilator, reached through the same link protocol as the real board.

:class:`UartSimTransport` is a :class:`~blockray.host_driver.serial_link.CreditedLink` whose raw
byte pipe is a localhost socket to a cocotb test (sim/uart_cocotb.py) that drives the simulated
``rx`` pin and decodes ``tx``: a virtual serial port. The simulation is
:class:`blockray.rtl.link.SerialLink` around the core, as on the ULX3S (:mod:`blockray.rtl.ulx3s`
adds only the PLL, the reset synchroniser and the pins), with a short bit time (``divisor``,
4 clock cycles by default, where the board runs 20 at 3 Mbaud). Built once per design with
:func:`blockray.sim.cocotb_support.build_verilator` (cached).

    link = UartSimTransport(EchoCore())      # or the board core
    link.send(b"...")
    link.recv(3)
"""

import json
import socket
import subprocess
import sys
import tempfile
import time
import weakref
from pathlib import Path

from .serial_link import CreditedLink
from .transport import TransportError

__all__ = ["UartSimTransport", "SIM_DIVISOR"]

#: clock cycles per bit in simulation (the UART's minimum)
SIM_DIVISOR = 4
_MODULE_DIR = Path(__file__).resolve().parent.parent / "sim"


def _stop(proc, sock):
    try:
        sock.close()
    except OSError:
        pass
    if proc.poll() is None:
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()


class UartSimTransport(CreditedLink):
    """``core`` (a component with ``i_bytes``/``o_bytes``) behind the UART link under Verilator.
    ``divisor``, ``fifo_depth``, ``result_depth``: :class:`~blockray.rtl.link.SerialLink`'s;
    ``name``: the Verilog top module (and cache entry)."""

    where = "the simulated board"

    def __init__(self, core, *, divisor=SIM_DIVISOR, fifo_depth=2048, result_depth=512, name="blockray_uart_sim",
                 startup_timeout=600, timeout=120.0, answer_timeout=60.0):
        from ..rtl.link import SerialLink
        from ..sim.cocotb_support import build_verilator

        super().__init__(timeout=timeout, answer_timeout=answer_timeout, break_seconds=0.05)
        top = SerialLink(core, divisor=divisor, fifo_depth=fifo_depth, result_depth=result_depth)
        self.build = build_verilator(top, name=name)
        self.workdir = Path(tempfile.mkdtemp(prefix="blockray_uart_"))
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        listener.settimeout(1.0)
        config = {"build_dir": str(self.build.build_dir), "toplevel": self.build.toplevel,
                  "test_dir": str(self.workdir), "module_dir": str(_MODULE_DIR),
                  "port": listener.getsockname()[1], "divisor": divisor}
        self.log_path = self.workdir / "simulator.log"
        self._log = open(self.log_path, "w")
        self._proc = subprocess.Popen([sys.executable, "-c", "from blockray.host_driver.uart_sim import _serve; _serve()",
                                       json.dumps(config)], stdout=self._log, stderr=subprocess.STDOUT,
                                      cwd=self.workdir)
        t0 = time.monotonic()
        self._sock = None
        while self._sock is None:
            try:
                self._sock, _ = listener.accept()
            except socket.timeout:
                if self._proc.poll() is not None or time.monotonic() - t0 > startup_timeout:
                    listener.close()
                    self._log.close()
                    raise TransportError(f"the UART simulation did not start; see {self.log_path}") from None
        listener.close()
        self._finalizer = weakref.finalize(self, _stop, self._proc, self._sock)
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


def _serve():
    """Child process: the cocotb test on the built simulation (returns when it ends)."""
    from cocotb_tools.runner import get_runner
    from ..sim.cocotb_support import verilator_env

    config = json.loads(sys.argv[1])
    verilator_env()
    sys.path.insert(0, config["module_dir"])
    get_runner("verilator").test(
        hdl_toplevel=config["toplevel"], test_module="uart_cocotb", build_dir=config["build_dir"],
        test_dir=config["test_dir"], hdl_toplevel_lang="verilog",
        extra_env={"BLOCKRAY_UART_PORT": str(config["port"]), "BLOCKRAY_UART_DIVISOR": str(config["divisor"])})

"""The transport over a board's serial port: the framed link (:mod:`blockray.host_driver.board.framed`)
over pyserial, for a real board (a ULX3S on its FT231X).

:class:`SerialPipe` is the raw byte pipe: the port's bytes, and a break as the reset (it resets
the board's link and core). :class:`SerialTransport` is a
:class:`~blockray.host_driver.board.framed.FramedTransport` over it, optionally through a
:class:`~blockray.host_driver.board.framed.FaultyPipe` (``--link-faults``). A missing port or a
silent board fails with one line (:class:`TransportError`, exit 2) within ``answer_timeout``
seconds: after the reset the board must answer a status frame.

    with SerialTransport("/dev/ttyUSB0", baud=DEFAULT_BAUD) as link:
        link.send(command_bytes)
        results = link.recv(n)
"""

import time

from ...link import DEFAULT_BAUD
from .framed import FaultyPipe, FramedTransport
from .transport import TransportError

__all__ = ["SerialPipe", "SerialTransport", "DEFAULT_BAUD"]


class SerialPipe:
    """The bytes of serial ``port`` at ``baud`` (pyserial); ``reset()`` holds a break for
    ``break_seconds`` and drops what came before. ``where`` names the port in errors."""

    def __init__(self, port, *, baud=DEFAULT_BAUD, write_timeout=5.0, break_seconds=0.05):
        import serial

        self.where, self.break_seconds = f"--port {port}", break_seconds
        try:
            self._serial = serial.Serial(port, baud, timeout=0, write_timeout=write_timeout)
        except (serial.SerialException, ValueError, OSError) as e:
            reason = str(e).split(": ", 1)[-1] if "could not open port" in str(e) else str(e)
            raise TransportError(f"{self.where}: cannot open the serial port ({reason})") from None

    def write(self, data):
        import serial
        try:
            self._serial.write(data)
        except serial.SerialException as e:
            raise TransportError(f"{self.where}: write failed ({e})") from None

    def read(self, timeout):
        s = self._serial
        s.timeout = timeout
        first = s.read(1)
        if not first:
            return b""
        s.timeout = 0
        return first + s.read(s.in_waiting or 0)

    def reset(self):
        self._serial.break_condition = True
        time.sleep(self.break_seconds)
        self._serial.reset_input_buffer()
        self._serial.break_condition = False

    def close(self):
        if self._serial.is_open:
            self._serial.close()


class SerialTransport(FramedTransport):
    """A board behind a serial port: ``port`` (e.g. ``/dev/ttyUSB0``), ``baud`` (the bitstream's;
    3 Mbaud by default), ``faults``: a :class:`~blockray.host_driver.board.framed.LinkFaults` to inject
    (``board``: which board's seeds). Opens the port and resets the board; a missing port or a
    board that does not answer raises :class:`TransportError`. ``timeout``: silence before a
    resend (a USB round trip is a few ms; the FT231X's latency timer is 16 ms by default)."""

    def __init__(self, port, *, baud=DEFAULT_BAUD, timeout=0.1, max_retries=32, answer_timeout=2.0, faults=None,
                 board=0):
        pipe = SerialPipe(port, baud=baud)
        if faults is not None:
            pipe = FaultyPipe(pipe, faults.injector(board, 0), faults.injector(board, 1))
        super().__init__(pipe, where=f"--port {port}", timeout=timeout, max_retries=max_retries,
                         answer_timeout=answer_timeout)
        self.port, self.baud = port, baud
        try:
            self.reset()
        except BaseException:
            self.close()
            raise

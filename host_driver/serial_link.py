"""Transports over the board's serial link: credits out, framed results in (:mod:`blockray.link`).

:class:`CreditedLink` is the host's half of the link protocol over any raw byte pipe: it sends
command bytes only against credits the board granted, parses the board's frames into result
bytes and grants, and resets the board with a break. :class:`SerialTransport` is that over a
serial port (pyserial): a real board, a ULX3S on its FT231X. The simulated real board
(``--board ulx3s-sim``) is the same class over the simulated UART pins.

A missing port or a silent board fails with one line (:class:`TransportError`, exit 2) within
``answer_timeout`` seconds: after the reset the board must grant its credits, and once running,
a board that sends nothing for ``timeout`` seconds while the host waits is reported too.

    with SerialTransport("/dev/ttyUSB0", baud=DEFAULT_BAUD) as link:
        link.send(command_bytes)
        results = link.recv(n)
"""

import time

from ..link import DEFAULT_BAUD, LinkHost
from .transport import Transport, TransportError

__all__ = ["CreditedLink", "SerialTransport", "DEFAULT_BAUD"]


class CreditedLink(Transport):
    """The link protocol over a raw byte pipe. Subclasses give ``_write(data)``,
    ``_read(timeout) -> bytes`` (what arrived, waiting at most ``timeout`` seconds for the
    first byte), ``_set_break(on)`` and ``_drop_input()``; ``where`` names the link in messages.

    ``timeout``: seconds of silence from a board the host waits on before giving up;
    ``answer_timeout``: seconds for the grants after a reset; ``break_seconds``: how long the
    break lasts (the board is silent meanwhile, so what it sent before is dropped).
    """

    where = "the link"

    def __init__(self, *, timeout=5.0, answer_timeout=2.0, break_seconds=0.05, vcd=None):
        super().__init__(vcd=vcd)
        self.timeout, self.answer_timeout, self.break_seconds = timeout, answer_timeout, break_seconds
        self._host = LinkHost()
        self._results = bytearray()
        self._sent = self._received = self._resets = 0

    # -- raw pipe (subclasses) -------------------------------------------------------------------

    def _write(self, data):
        raise NotImplementedError

    def _read(self, timeout):
        raise NotImplementedError

    def _set_break(self, on):
        raise NotImplementedError

    def _drop_input(self):
        raise NotImplementedError

    # -- Transport --------------------------------------------------------------------------------

    def _pump(self, timeout):
        """Read what the board sent (waiting up to ``timeout`` s); returns whether anything came."""
        data = self._read(timeout)
        if data:
            self._received += len(data)
            self._results += self._host.feed(data)
        return bool(data)

    def send(self, data):
        data = memoryview(bytes(data))
        while data:
            if self._host.credits == 0:
                if not self._pump(self.timeout) and self._host.credits == 0:
                    raise TransportError(f"{self.where}: the board stopped taking commands (no credit for "
                                         f"{self.timeout:g} s)")
                continue
            n = min(self._host.credits, len(data))
            self._write(bytes(data[:n]))
            self._host.spend(n)
            self._sent += n
            data = data[n:]
            self._pump(0)

    def recv(self, count, *, timeout=None):
        silence = self.timeout if timeout is None else timeout
        last = time.monotonic()
        while len(self._results) < count:
            if self._pump(min(0.1, silence)):
                last = time.monotonic()
            elif time.monotonic() - last > silence:
                raise TransportError(f"{self.where}: the board sent {len(self._results)} of {count} result bytes "
                                     f"and then nothing for {silence:g} s")
        out = bytes(self._results[:count])
        del self._results[:count]
        return out

    def reset(self):
        """Break (reset the link and the board), drop what came before, wait for the grants."""
        self._set_break(True)
        time.sleep(self.break_seconds)
        self._drop_input()
        self._set_break(False)
        self._host.reset()
        self._results.clear()
        self._resets += 1
        deadline = time.monotonic() + self.answer_timeout
        while self._host.credits == 0:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TransportError(f"{self.where}: no answer from the board within {self.answer_timeout:g} s "
                                     f"of a reset (is the bitstream loaded, at this baud rate?)")
            self._pump(min(left, 0.1))

    @property
    def credits(self):
        return self._host.credits

    def stats(self):
        return {"bytes_sent": self._sent, "bytes_received": self._received, "credits_granted": self._host.granted,
                "resets": self._resets}


class SerialTransport(CreditedLink):
    """A board behind a serial port (pyserial): ``port`` (e.g. ``/dev/ttyUSB0``), ``baud``
    (the bitstream's; 3 Mbaud by default). Opens the port and resets the board; a missing port
    or a board that does not answer raises :class:`TransportError`."""

    def __init__(self, port, *, baud=DEFAULT_BAUD, **kw):
        import serial

        super().__init__(**kw)
        self.port, self.baud = port, baud
        self.where = f"--port {port}"
        try:
            self._serial = serial.Serial(port, baud, timeout=0, write_timeout=self.timeout)
        except (serial.SerialException, ValueError, OSError) as e:
            reason = str(e).split(": ", 1)[-1] if "could not open port" in str(e) else str(e)
            raise TransportError(f"{self.where}: cannot open the serial port ({reason})") from None
        try:
            self.reset()
        except BaseException:
            self._serial.close()
            raise

    def _write(self, data):
        import serial
        try:
            self._serial.write(data)
        except serial.SerialException as e:
            raise TransportError(f"{self.where}: write failed ({e})") from None

    def _read(self, timeout):
        s = self._serial
        s.timeout = timeout
        first = s.read(1)
        if not first:
            return b""
        s.timeout = 0
        return first + s.read(s.in_waiting or 0)

    def _set_break(self, on):
        self._serial.break_condition = on

    def _drop_input(self):
        self._serial.reset_input_buffer()

    def close(self):
        if getattr(self, "_serial", None) is not None and self._serial.is_open:
            self._serial.close()

"""One board's link, at the byte level: the only thing a new back-end (a serial port, a simulator,
a board on a cluster worker) has to implement.

The Glasgow pattern (GlasgowEmbedded/glasgow, software/glasgow/abstract.py): the host API
(:class:`~blockray.host_driver.board.driver.BoardDriver`) talks to an abstract transport and does not
know whether a simulator or hardware answers. One transport per board; the driver holds P of
them. Bytes are the wire format of :mod:`blockray.protocol` (commands out, results in).

Simulation transports may buffer what :meth:`Transport.send` gets and run the simulator only when
:meth:`Transport.recv` needs bytes (lazily). :meth:`Transport.expect` lets the driver say how
many result bytes it will ask for next, so a simulator running in another process can start at
once and the P boards run concurrently; a hardware link ignores it.
"""

from abc import ABC, abstractmethod

from ...errors import BlockrayError

__all__ = ["Transport", "TransportError"]


class TransportError(BlockrayError):
    """The link or the board behind it did not answer as the protocol says."""


class Transport(ABC):
    """One board's byte link. ``vcd``: where a simulation writes its waveform (hardware: None).

    Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, *, vcd=None):
        self.vcd = vcd

    @abstractmethod
    def send(self, data: bytes):
        """Queue command bytes for the board (they may go out later, at the latest in
        :meth:`recv`)."""

    @abstractmethod
    def recv(self, count: int, *, timeout=None) -> bytes:
        """Exactly ``count`` result bytes, in order. Raises :class:`TransportError` if they do not
        come within ``timeout`` seconds (None: as long as it takes)."""

    @abstractmethod
    def reset(self):
        """Reset the board. Queued commands, commands in the board and results not yet received
        are lost, and so is the board's memory (whoever resets it reloads it)."""

    def expect(self, count: int):
        """Hint: the next :meth:`recv` calls will ask for ``count`` bytes in all (a simulation
        may start running now)."""

    def close(self):
        """Release the link (stop a simulator)."""

    def stats(self):
        """Measurements of the link (dict; simulators add their clock cycles and run time)."""
        return {}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

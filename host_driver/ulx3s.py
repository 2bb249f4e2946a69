"""The ULX3S back-ends' transports: a real board on a serial port, and the same top level
simulated (UART included) under Verilator.

Both open one board's link for the host driver (``transport(params, board)`` of
:class:`~blockray.host_driver.driver.BoardDriver`, issue 12) and reset it; the driver then sends
``IDENTIFY`` and checks the bitstream's configuration before it uploads anything. Registered in
host_driver/backends.py as::

    register(Backend("ulx3s", "a ULX3S board on a serial port (--port, --baud)", ...))
    register(Backend("ulx3s-sim", "the ULX3S top level, UART included, under Verilator",
                     _driven("ulx3s-sim", ulx3s_sim_transport)))
"""

from .serial_link import DEFAULT_BAUD, SerialTransport
from .uart_sim import SIM_DIVISOR, UartSimTransport

__all__ = ["ulx3s_transport", "ulx3s_sim_transport"]


def ulx3s_transport(port, *, baud=DEFAULT_BAUD, faults=None, board=0):
    """Board behind serial ``port`` (a real ULX3S running ``blockray bitstream``'s bitstream), over
    the framed link; ``faults``: a :class:`~blockray.host_driver.framed.LinkFaults` to inject."""
    return SerialTransport(port, baud=baud, faults=faults, board=board)


def ulx3s_sim_transport(params, board=0, *, vcd=None, host=None, faults=None, fifo_depth=2048):
    """The board core for ``params`` behind the UART and the framed link under Verilator (bit
    time ``SIM_DIVISOR`` cycles); ``faults``: as :func:`ulx3s_transport`. ``vcd``/``host`` are not
    supported (the link sets the host's timing)."""
    from ..errors import ParameterError
    from ..rtl.core import BoardCore
    if vcd is not None or host is not None:
        raise ParameterError("--board ulx3s-sim: the UART sets the host's timing; no --vcd or --host-timing")
    return UartSimTransport(BoardCore(params), divisor=SIM_DIVISOR, fifo_depth=fifo_depth, faults=faults,
                            board=board, name="blockray_ulx3s_sim")

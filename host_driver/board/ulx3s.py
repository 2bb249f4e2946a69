"""The ULX3S back-ends' transports: a real board on a serial port, and the same top level
simulated (UART included) under Verilator.

Both open one board's link for the host driver (``transport(params, board)`` of
:class:`~blockray.host_driver.board.driver.BoardDriver`) and reset it; the driver then sends
``IDENTIFY`` and checks the bitstream's configuration before it uploads anything. The real
board's back-end (``--board ulx3s``, registered in host_driver/board/backends.py) is
:func:`ulx3s_board`: it opens every board's serial link first (a missing port or a silent board
fails there, in seconds) and takes the boards' memories, B and processor cell from their IDENTIFY
replies.
"""

from ...cell import Cell
from ...errors import ParameterError, option
from ...protocol import BoardProtocol, identity_cell
from ...params import MIN_BITS
from .serial_link import DEFAULT_BAUD, SerialTransport
from .uart_sim import SIM_DIVISOR, UartSimTransport

__all__ = ["ulx3s_board", "ulx3s_transport", "ulx3s_sim_transport", "CAPACITY_HINT"]

#: what to change when a scene does not fit the bitstream's memories
CAPACITY_HINT = ("rebuild the bitstream with larger memories (blockray bitstream --patch-depth, --voxel-depth), "
                 "spread the scene over more boards (--boards with a --port each), or subdivide it less "
                 "(--max-edge)")


def ulx3s_board(params, ports, *, baud=DEFAULT_BAUD, partition="deal", open_link=None, faults=None, cell=None):
    """The host driver over ULX3S boards, one behind each of ``ports`` (``params.boards`` of them).

    Every link is opened and reset first, then every board is asked for its configuration
    (IDENTIFY): the boards' memories and, unless ``params.bits`` asks for a B, their B are what board 0
    answers; R and S are ``params``' (the driver checks every board against the whole
    configuration before it uploads). ``open_link(port, baud=)``: the transport of one port
    (default :func:`ulx3s_transport`; with ``faults``, a
    :class:`~blockray.host_driver.board.framed.LinkFaults`, it gets ``faults=`` and ``board=`` too).
    ``cell``: the processor cell the host expects (``--cell``); None (the default) takes board 0's
    (``blockray bitstream --cell``), as it takes B and the memories. The cell sets the drain the host
    counts after each batch."""
    from .driver import BoardDriver
    open_link = open_link or ulx3s_transport
    ports = (ports,) if isinstance(ports, str) else tuple(ports or ())
    if not ports:
        raise ParameterError(f"{option('port')}: {option('backend')} ulx3s needs the board's serial port, e.g. "
                             f"{option('port')} /dev/ttyUSB0",
                             parameter="port")
    if len(ports) != params.boards:
        raise ParameterError(f"{option('boards')}: {params.boards} boards need {params.boards} ports, {option('port')} names "
                             f"{len(ports)}", parameter="boards")
    links = []
    try:
        for b, port in enumerate(ports):
            links.append(open_link(port, baud=baud, **({} if faults is None else {"faults": faults, "board": b})))
        # IDENTIFY's reply reads alike under any B: the protocol is built for one before B is known
        built = BoardDriver.identities_of(links, BoardProtocol(params.with_(bits=params.bits or MIN_BITS)))[0]
    except BaseException:
        for link in links:
            link.close()
        raise
    expect = params.with_(bits=params.bits or built["bits"], patch_depth=built["patch_depth"],
                          voxel_depth=built["voxel_depth"])
    cell = identity_cell(built) if cell is None else cell
    return BoardDriver(expect, fit=False, name="ulx3s", partition=partition, hint=CAPACITY_HINT, cell=cell,
                       transport=lambda p, b: links[b])


def ulx3s_transport(port, *, baud=DEFAULT_BAUD, faults=None, board=0):
    """Board behind serial ``port`` (a real ULX3S running ``blockray bitstream``'s bitstream), over
    the framed link; ``faults``: a :class:`~blockray.host_driver.board.framed.LinkFaults` to inject."""
    return SerialTransport(port, baud=baud, faults=faults, board=board)


def ulx3s_sim_transport(params, board=0, *, vcd=None, host=None, faults=None, fifo_depth=2048, cell=Cell()):
    """The board core for ``params`` with ``cell`` behind the UART and the framed link under
    Verilator (bit time ``SIM_DIVISOR`` cycles); ``faults``: as :func:`ulx3s_transport`.
    ``vcd``/``host`` are not supported (the link sets the host's timing)."""
    from ...rtl.core import BoardCore
    if vcd is not None or host is not None:
        raise ParameterError(f"{option('backend')} ulx3s-sim: the UART sets the host's timing; no {option('vcd')} "
                             f"or {option('host')}")
    return UartSimTransport(BoardCore(params, rays=True, cell=cell), divisor=SIM_DIVISOR, fifo_depth=fifo_depth, faults=faults,
                            board=board, name="blockray_ulx3s_sim")

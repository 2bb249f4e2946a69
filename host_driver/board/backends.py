"""The board back-ends by name: one registry for ``render.make_board`` and the CLI's ``--board``
(its choices and help text come from here).

A back-end is a factory ``(params, *, partition, vcd, host) -> Board`` (and ``port``,
``baud`` for a board on serial ports). The driven ones are a
:class:`~blockray.host_driver.board.driver.BoardDriver` over one transport per board
(host_driver/board/simulated.py); the real ULX3S (``ulx3s``, host_driver/board/ulx3s.py) is the driver over
serial links it opens itself, ``ulx3s-sim`` its top level under Verilator.
"""

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Callable

from ...errors import ParameterError, option
from ...cell import CELLS as _CELLS, Cell, check_cell
from ...link import DEFAULT_BAUD
from ...memory import check_partition

__all__ = ["Backend", "BACKENDS", "register", "backend", "make_board", "build_board", "check_board"]


@dataclass(frozen=True)
class Backend:
    """``name``; ``help`` (one phrase for ``--board``); ``factory``; ``quantises``: the board
    quantises the scene (``--bits``, ``--partition`` apply); ``waveform``: it can write ``--vcd``;
    ``host_timing``: it takes random host idle / back-pressure (``--link-*``); ``cells``: the
    processor cells it can be built with (``--cell``); ``faults``: its link is framed and can
    inject faults (``--link-faults``); ``serial``: a real board on serial ports (``--port``,
    ``--baud``)."""
    name: str
    help: str
    factory: Callable
    quantises: bool = True
    waveform: bool = False
    host_timing: bool = False
    cells: tuple = ("exact",)
    faults: bool = False
    serial: bool = False


BACKENDS = {}


def register(entry):
    if entry.name in BACKENDS:
        raise ValueError(f"board back-end {entry.name!r} is registered twice")
    BACKENDS[entry.name] = entry
    return entry


def backend(name):
    """The registered back-end ``name``, or ParameterError naming the choices."""
    try:
        return BACKENDS[name]
    except KeyError:
        raise ParameterError(f"{option('backend')} must be one of {', '.join(BACKENDS)}, not {name!r}",
                             parameter="board") from None


def make_board(name, params=None, *, partition="deal", cell=Cell(), vcd=None, host=None, faults=None, port=(),
               baud=DEFAULT_BAUD):
    """Build back-end ``name`` for ``params`` (default :class:`~blockray.params.BoardParams` with
    B chosen per scene); the keywords are the fields of
    :class:`~blockray.host_driver.render.options.BoardOptions` (see :func:`build_board`)."""
    from ...params import BoardParams
    board = SimpleNamespace(backend=name, params=params or BoardParams(bits=None), partition=partition, cell=cell,
                            vcd=vcd, host=host, faults=faults, port=port, baud=baud)
    check_board(board)
    return build_board(board)


def check_board(options):
    """ParameterError if back-end ``options.backend`` cannot be built as ``options`` (a
    :class:`~blockray.host_driver.render.options.BoardOptions`) asks: a cell, partition,
    waveform, host timing or fault injection it does not have."""
    entry, name, kind = backend(options.backend), options.backend, check_cell(options.cell).kind
    check_partition(options.partition)
    if kind not in entry.cells:
        able = " or ".join(n for n, b in BACKENDS.items() if kind in b.cells)
        raise ParameterError(f"{option('cell')} {kind} needs a board built with that cell ({option('backend')} {able}), "
                             f"not {name!r}",
                             parameter="cell")
    if not entry.quantises and options.partition != "deal":
        raise ParameterError(f"{option('partition')} applies to the hardware's boards; the golden board holds the whole scene",
                             parameter="partition")
    if options.vcd is not None and not entry.waveform:
        able = " or ".join(n for n, b in BACKENDS.items() if b.waveform)
        raise ParameterError(f"{option('vcd')} needs a simulated RTL board ({option('backend')} {able}), not {name!r}",
                             parameter="vcd")
    if options.host is not None and not entry.host_timing:
        able = " or ".join(n for n, b in BACKENDS.items() if b.host_timing)
        raise ParameterError(f"{option('host')} need a board simulated cycle by cycle ({option('backend')} {able}), "
                             f"not {name!r}", parameter="host")
    if options.faults is not None and not entry.faults:
        able = " or ".join(n for n, b in BACKENDS.items() if b.faults)
        raise ParameterError(f"{option('link_faults')} needs a board with a framed link ({option('backend')} {able}), "
                             f"not {name!r}",
                             parameter="link_faults")


def build_board(options, outputs=None):
    """The board of a :class:`~blockray.host_driver.render.options.BoardOptions` (checked by
    :func:`check_board` when the options were built). ``params.bits=None`` lets the board choose
    B for the scene; ``vcd`` (a path) a waveform of a simulated board (board b > 0 writes ``FILE.b``),
    given an ``outputs`` (:class:`blockray.atomic.Outputs`) written to temporaries that are
    renamed over the files with that batch (close the board before the batch ends);
    ``host``: the host's timing on a simulated board's link: ``(idle, backpressure, seed)``, two
    :class:`blockray.sim.drive.HostTiming` and a seed. ``cell``: the boards' processor
    :class:`~blockray.cell.Cell`; the back-ends that build the board's model or RTL take a
    filtering one. ``faults``: a :class:`~blockray.host_driver.board.framed.LinkFaults` to
    inject on every board's link. ``port``, ``baud``: a real board's serial links."""
    entry, o = backend(options.backend), options
    extra = {}
    if o.faults is not None:
        extra["faults"] = o.faults
    if o.cell.filtered:
        extra["cell"] = o.cell
    if entry.serial:
        extra.update(port=o.port, baud=o.baud)
    vcd = o.vcd
    if vcd is not None and outputs is not None:
        vcd = [outputs.reserve(_wave(vcd, b), "--vcd") for b in range(o.params.boards)]
    return entry.factory(o.params, partition=o.partition, vcd=vcd, host=o.host, **extra)


def _wave(vcd, b):
    """Board b's waveform file: of a path ``vcd`` (FILE, FILE.1, ...) or a list of one per board."""
    if isinstance(vcd, list):
        return vcd[b]
    return None if vcd is None else (str(vcd) if b == 0 else f"{vcd}.{b}")


def _golden(params, *, partition, vcd, host):
    from .golden import GoldenBoard
    return GoldenBoard()


def _model(params, *, partition, vcd, host, cell=Cell()):
    from ...sim.model import ModelBoard
    return ModelBoard(params, partition=partition, cell=cell)


def _driven(name, open_transport):
    def factory(params, *, partition, vcd, host, **extra):
        from .driver import BoardDriver
        return BoardDriver(params, partition=partition, name=name, cell=extra.get("cell", Cell()),
                           transport=lambda p, b: open_transport(p, b, vcd=_wave(vcd, b), host=host, **extra))
    return factory


def _timing(host, b):
    idle, backpressure, seed = host or (None, None, 0)
    return {"idle": idle, "backpressure": backpressure, "seed": seed * 1000 + b}


def _amaranth(p, b, *, vcd, host, **cell):
    from .simulated import AmaranthTransport
    return AmaranthTransport(p, vcd=vcd, **_timing(host, b), **cell)


def _verilator(p, b, *, vcd, host, **cell):
    from .native import NativeTransport
    return NativeTransport(p, vcd=vcd, **_timing(host, b), **cell)


def _model_link(p, b, *, vcd, host, faults=None, **cell):
    from .framed import FaultyPipe, FramedTransport, ModelBoardLink
    from .simulated import ModelTransport
    pipe = ModelBoardLink(ModelTransport(p, **cell))
    if faults is not None:
        pipe = FaultyPipe(pipe, faults.injector(b, 0), faults.injector(b, 1))
    return FramedTransport(pipe, where=f"model-link board {b}")


register(Backend("golden", "exact reference on the float scene", _golden, quantises=False))
register(Backend("model", "bit-exact model of the hardware; default", _model, cells=_CELLS))
register(Backend("model-link", "the host driver and the board's framed byte link answered by the bit-exact "
                 "model (no RTL; link traffic, --link-faults)", _driven("model-link", _model_link), cells=_CELLS,
                 faults=True))
register(Backend("amaranth", "the board's RTL in the Amaranth simulator: small scenes, debugging",
                 _driven("amaranth", _amaranth), waveform=True, host_timing=True, cells=_CELLS))
register(Backend("verilator", "the board's Verilog under Verilator, clocked by a native C++ loop; builds once per "
                 "design, cached", _driven("verilator", _verilator), waveform=True, host_timing=True, cells=_CELLS))


def _ulx3s_sim(p, b, *, vcd, host, faults=None, **cell):
    from .ulx3s import ulx3s_sim_transport
    return ulx3s_sim_transport(p, b, vcd=vcd, host=host, faults=faults, **cell)


def _ulx3s(params, *, partition, vcd, host, port=(), baud=None, faults=None, **cell):
    from .ulx3s import ulx3s_board
    return ulx3s_board(params, port, baud=baud, partition=partition, faults=faults, **cell)


# the cells `blockray bitstream` builds
register(Backend("ulx3s-sim", "the ULX3S top level, UART and framed link included, under Verilator "
                 "(bit-identical to model; --link-faults)", _driven("ulx3s-sim", _ulx3s_sim), faults=True,
                 cells=("exact", "lean")))
register(Backend("ulx3s", "a ULX3S-85F board on a serial port (--port, --baud; docs/ulx3s.md)", _ulx3s,
                 serial=True, faults=True, cells=("exact", "lean")))


def help_text():
    """``--board``'s help: every back-end with its phrase."""
    return "board back-end: " + "; ".join(f"{n} ({b.help})" for n, b in BACKENDS.items())

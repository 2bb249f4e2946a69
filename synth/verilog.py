"""The synthesisable units, built from :class:`~blockray.params.BoardParams`, and their Verilog.

Units (``UNITS``):

``processor``  :class:`~blockray.rtl.processor.Intersector`: one processor cell with its shooter
               and receiver units (the 1 x 1 array) behind stream ports. Uses ``bits``.
``cell``       :class:`~blockray.rtl.processor.Processor` alone (its terms come from the units of
               its row and column). Uses ``bits``.
``array``      :class:`~blockray.rtl.array.ProcessorArray`: R x S cells, S shooter units, R
               receiver units. Uses ``bits``, ``rows``, ``cols``.
``board``      :class:`~blockray.rtl.board.BoardTop`: command/result streams, patch memory and
               voxel table, the R x S array. Uses every parameter but ``boards``.

``cell`` (a :class:`~blockray.cell.Cell`, ``--cell``): ``exact`` (default) builds the above;
``filtered`` builds the filtered cell of :mod:`blockray.rtl.filtered` (``processor``:
:class:`FilteredIntersector`, ``cell``: :class:`FilteredProcessor`, ``array``:
:class:`FilteredArray` with its shared exact unit, ``board``: ``BoardTop(cell=Cell("filtered"))``;
default format d_k exact and w_k at 18 bits);
``lean`` the lean cell of :mod:`blockray.rtl.lean` (``array``: :class:`LeanArray` with its
shared exact unit and end-point memory, its patch memory's read port a top-level port;
``processor``: the 1 x 1 LeanArray; ``cell``: the filtered cell at the lean format, 9 x 9 bits;
``board``: ``BoardTop(cell=Cell("lean"))``, the array's read port on the patch memory).

    text = unit_verilog("array", BoardParams(rows=2, cols=2, bits=16))
    text = unit_verilog("processor", target="ecp5")    # products on registered MULT18X18D

``target`` (:mod:`blockray.synth.target`): ``generic`` (default) is the portable netlist
(``*`` and fabric registers), ``ecp5`` instantiates the ECP5 DSP primitive for every product
except those of the ``fabric_units`` (left as ``*``, for LUT multipliers).
"""

from .. import hdl

from ..atomic import write_file
from ..errors import ParameterError
from ..cell import Cell, check_cell
from ..params import BoardParams
from .target import target_platform

__all__ = ["UNITS", "MAX_MEMORY_BITS", "board_memory_bits", "build_unit", "unit_verilog",
           "write_verilog"]

UNITS = ("processor", "cell", "array", "board")

#: Largest board memory (patch memory + voxel table) that is built: 16 Mbit, 4.5 x the block RAM
#: of the largest ECP5 (LFE5U-85F: 208 x 18 Kbit). Amaranth's conversion needs 130-155 bytes of
#: host memory per bit: the default board (5.0 Mbit) took 95 s and 0.77 GB, ``--patch-depth
#: 65536`` (17.2 Mbit) 344 s and 2.2 GB (docs/input.md).
MAX_MEMORY_BITS = 1 << 24


def board_memory_bits(params):
    """(patch memory bits, voxel table bits) of the board for ``params``."""
    from ..rtl.memctrl import patch_layout
    from ..protocol import BoardProtocol
    return (params.patch_depth * patch_layout(params.bits).size,
            params.voxel_depth * BoardProtocol(params).table_entry_layout.size)


def _check_memory(params):
    patch, table = board_memory_bits(params)
    if patch + table > MAX_MEMORY_BITS:
        raise ParameterError(
            f"the board's memories would hold {patch + table:.3g} bits (patch memory {params.patch_depth} "
            f"words, voxel table {params.voxel_depth} entries), more than {MAX_MEMORY_BITS} (16 Mbit, "
            f"4.5 x the largest ECP5's block RAM; converting them needs ~150 bytes of memory per bit)",
            parameter="patch_depth" if patch >= table else "voxel_depth")


def _check_unit(unit):
    if unit not in UNITS:
        raise ParameterError(f"unit must be one of {', '.join(UNITS)}, not {unit!r}")
    return unit


def _lean_unit(unit, params, fmt):
    from ..rtl.filtered import FilteredProcessor
    from ..rtl.lean import LeanArray
    if unit == "cell":
        return FilteredProcessor(fmt, carry_chains=True)
    rows, cols = (1, 1) if unit == "processor" else (params.rows, params.cols)
    return LeanArray(params.bits, rows, cols, fmt=fmt, address_bits=max(1, (params.patch_depth - 1).bit_length()))


def _filtered_unit(unit, params, cell):
    from ..rtl.filtered import FilteredArray, FilteredIntersector, FilteredProcessor
    fmt = cell.format
    if unit == "board":             # the lean board too: its array re-reads the patch memory
        from ..rtl.board import BoardTop
        _check_memory(params)
        return BoardTop(params, cell=cell)
    if cell.lean:
        return _lean_unit(unit, params, fmt)
    if unit == "processor":
        return FilteredIntersector(params.bits, fmt)
    if unit == "array":
        return FilteredArray(params.bits, params.rows, params.cols, fmt=fmt)
    return FilteredProcessor(fmt)


def build_unit(unit, params=None, cell=Cell()):
    """A fresh component of ``unit`` configured by ``params`` (default :class:`BoardParams`),
    with ``cell`` (a :class:`~blockray.cell.Cell`; its format chosen at ``params.bits``)."""
    _check_unit(unit)
    params = BoardParams() if params is None else params
    if not isinstance(params, BoardParams):
        raise ParameterError(f"synthesis parameters must be BoardParams, not {params!r}")
    cell = check_cell(cell).at(params.bits)
    if cell.filtered:
        return _filtered_unit(unit, params, cell)
    if unit == "processor":
        from ..rtl.processor import Intersector
        return Intersector(params.bits)
    if unit == "cell":
        from ..rtl.processor import Processor
        return Processor(params.bits)
    if unit == "array":
        from ..rtl.array import ProcessorArray
        return ProcessorArray(params.bits, params.rows, params.cols)
    from ..rtl.board import BoardTop
    _check_memory(params)
    return BoardTop(params)


def unit_verilog(unit, params=None, *, name=None, target="generic", fabric_units=(), cell=Cell()):
    """Readable Verilog (no source attributes) of ``unit`` with ``cell`` for ``target``
    (``generic`` or ``ecp5``, with ``fabric_units``); the top module is ``name`` (default
    ``blockray_<unit>``)."""
    platform = target_platform(target, fabric_units)
    component = build_unit(unit, params, cell)
    return hdl.convert(component, name=name or f"blockray_{unit}", emit_src=False, platform=platform)


def write_verilog(path, unit, params=None, *, name=None, target="generic", fabric_units=(), cell=Cell()):
    """Write :func:`unit_verilog` to ``path``; returns the text."""
    text = unit_verilog(unit, params, name=name, target=target, fabric_units=fabric_units, cell=cell)
    write_file(path, "--out", lambda f: f.write(text))
    return text

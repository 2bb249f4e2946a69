"""The board's host protocol, in one place: opcodes, typed command records, record layouts, and
the compact byte format on the link.

One definition serves the gateware (``rtl/board.py`` executes the wide command record,
``rtl/core.py`` decodes the byte stream into it), the bit-exact model (``sim/model.py`` executes
the typed commands), the host driver (``host_driver/board/driver.py`` encodes them and decodes results)
and the testbenches. docs/board-protocol.md embeds :func:`describe`'s output (a test keeps them
equal).

**Command records.** One small frozen dataclass per opcode (:class:`WritePatch` ...
:class:`Identify`); ``command.op`` is its :class:`Op`. :meth:`BoardProtocol.record` packs one into
the board's internal command record ``{op, arg}`` (:attr:`BoardProtocol.command_layout`: ``arg``
a union with one member per command that has operands; the RTL's command register holds it).

**Wire format** (what crosses the link, :meth:`BoardProtocol.encode`): a command is a header byte
(bits 3:0 the opcode; for LOAD_POINTS bits 5:4 = points - 1) followed by the bits of its ``arg``
member only, least significant first, in ``ceil(bits / 8)`` bytes (LOAD_POINTS: only the slots it
carries). Widths come from the scene's B and the memory depths, so a VOXEL command of a
32 768-entry voxel table is 3 bytes. A result is the low ``ceil((2 + member bits) / 8)`` bytes of
the result record ``{kind, data}``: a 2-bit :class:`ResultKind` tag, then the R x S blocked bits
(END_BLOCK), the counters (READ_COUNTERS) or the board's identity (IDENTIFY). The first byte of a
result tells its length.

Address widths come from the memory sizes ("model only what a scene needs"): a patch address is
``ceil(log2(patch_depth))`` bits, a record count ``bits_for(patch_depth)`` (a voxel may hold the
whole memory), a voxel number ``ceil(log2(voxel_depth))`` bits. :func:`fit_params` gives the
smallest memories for a scene's partition and :func:`check_capacity` raises
:class:`~blockray.errors.CapacityError` before anything is simulated.
"""

import enum
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from amaranth.hdl import Shape, unsigned
from amaranth.lib import data
from amaranth.utils import bits_for, ceil_log2

from .cell import CELLS, Cell, check_cell
from .errors import CapacityError, ParameterError
from .filtered import FilterFormat
from .params import BoardParams
from .records import leaves, pack, pack_bytes, patch_layout, point_layout, unpack

__all__ = ["Op", "POINTS_PER_LOAD", "MAGIC", "VERSION", "ResultKind", "COUNTERS", "COUNTER_WIDTH",
           "IDENTITY_FIELDS", "CELL_FIELDS", "cell_identity", "identity_cell", "RAYS_VERSION", "Command",
           "WritePatch", "WriteVoxel", "BeginBlock", "LoadReceiver",
           "LoadShooter", "LoadPoints", "Voxel", "EndBlock", "ReadCounters", "Identify", "COMMANDS",
           "BoardProtocol", "BoardResult", "ResultReader", "fit_params", "check_capacity", "describe"]


class Op(enum.IntEnum):
    """Board command opcodes (bits 3:0 of a command's header byte and the RTL's ``op`` field)."""
    WRITE_PATCH = 0
    WRITE_VOXEL = 1
    BEGIN_BLOCK = 2
    LOAD_RECEIVER = 3
    LOAD_SHOOTER = 4
    VOXEL = 5
    END_BLOCK = 6
    READ_COUNTERS = 7
    LOAD_POINTS = 8
    IDENTIFY = 9


#: points one LOAD_POINTS command carries (a block of R receivers and S shooters needs
#: ceil((R + S) / POINTS_PER_LOAD) of them)
POINTS_PER_LOAD = 4
#: IDENTIFY's ``magic`` and ``version``: the host checks both before it trusts a board
#: (version 4 added the cell fields; a board of versions 2 and 3 cannot say its cell)
MAGIC = 0xB10C
VERSION = 4
#: the ``version`` a board built with the block sequencer answers: the same fields and commands,
#: and it takes the commands of rays made on the board too (:mod:`blockray.board_rays`)
RAYS_VERSION = 5


class ResultKind(enum.IntEnum):
    """What a result record holds (its 2-bit tag)."""
    BLOCKED = 0     # END_BLOCK: the R x S blocked bits
    COUNTERS = 1    # READ_COUNTERS: the counter snapshot
    IDENTITY = 2    # IDENTIFY: the built configuration


#: the counters of a READ_COUNTERS result, in layout order (docs/board-protocol.md defines them)
COUNTERS = ("cycles", "busy", "tests_issued", "tests_useful", "stalls")
#: bits per counter: 2**48 cycles is 32 days at 100 MHz
COUNTER_WIDTH = 48
#: IDENTIFY's result fields and widths
IDENTITY_FIELDS = {"magic": 16, "version": 8, "rows": 8, "cols": 8, "bits": 8,
                   "patch_depth": 32, "voxel_depth": 32,
                   "cell": 8, "d_bits": 8, "w_bits": 8, "w_input_bits": 8}
#: IDENTIFY's fields that say the processor cell (:func:`identity_cell` reads them back)
CELL_FIELDS = ("cell", "d_bits", "w_bits", "w_input_bits")


def cell_identity(cell):
    """IDENTIFY's cell fields of ``cell`` (its format chosen): the kind's index in
    :data:`~blockray.cell.CELLS` and the filter's mantissa widths (0: none)."""
    f = cell.format
    return {"cell": CELLS.index(cell.kind), "d_bits": f.d_bits if f else 0, "w_bits": f.w_bits if f else 0,
            "w_input_bits": (f.w_input_bits or 0) if f else 0}


def identity_cell(identity):
    """The :class:`~blockray.cell.Cell` an IDENTIFY result names (its format chosen)."""
    kind = identity["cell"]
    if kind >= len(CELLS):
        raise ParameterError(f"IDENTIFY names cell {kind}, not one of 0..{len(CELLS) - 1} ({', '.join(CELLS)})",
                             parameter="cell")
    if CELLS[kind] == "exact":
        return Cell()
    return Cell(CELLS[kind], FilterFormat(identity["d_bits"], identity["w_bits"], identity["w_input_bits"] or None))


# -- typed command records ------------------------------------------------------------------------

def _point(p):
    return dict(zip("xyz", (int(c) for c in p)))


#: an end point's index, by ``shooter``: (its name in errors, the BoardParams field bounding it)
_END_POINT_INDEX = {False: ("receiver row", "rows"), True: ("shooter column", "cols")}


def _end_point(proto, shooter, index, point):
    """Check a receiver row / shooter column index against the array; the point's record value."""
    what, param = _END_POINT_INDEX[bool(shooter)]
    proto.check(index, getattr(proto.params, param), what, param)
    return _point(point)


@dataclass(frozen=True)
class Command:
    """A board command. Subclasses set ``op`` and ``member`` (their ``arg`` union member, or
    None) and give the member's value with :meth:`arg`."""
    op: ClassVar[Op]
    member: ClassVar[str] = None

    def arg(self, proto):
        return {}


@dataclass(frozen=True)
class WritePatch(Command):
    """Patch memory word ``address`` := ``patch`` (a packed :func:`~blockray.records.patch_layout`)."""
    address: int
    patch: int
    op: ClassVar[Op] = Op.WRITE_PATCH
    member: ClassVar[str] = "write_patch"

    def arg(self, proto):
        p = proto.params
        proto.check(self.address, p.patch_depth, "patch address", "patch_depth")
        return {"address": self.address, "patch": unpack(patch_layout(p.bits), self.patch)}


@dataclass(frozen=True)
class WriteVoxel(Command):
    """Voxel table entry ``voxel`` := (``start``, ``count``): records start .. start + count - 1."""
    voxel: int
    start: int
    count: int
    op: ClassVar[Op] = Op.WRITE_VOXEL
    member: ClassVar[str] = "write_voxel"

    def arg(self, proto):
        p = proto.params
        proto.check(self.voxel, p.voxel_depth, "voxel", "voxel_depth")
        start, count = int(self.start), int(self.count)
        if start < 0 or count < 0 or start + count > p.patch_depth:
            raise CapacityError(f"voxel {self.voxel}: records {start}..{start + count - 1} are outside "
                                f"patch memory (patch_depth {p.patch_depth})")
        if count == 0:
            start = 0       # an empty voxel's start is never read; keep it in range
        return {"voxel": self.voxel, "entry": {"start": start, "count": count}}


@dataclass(frozen=True)
class BeginBlock(Command):
    """Clear the row/column valid masks; the next record clears the accumulators."""
    op: ClassVar[Op] = Op.BEGIN_BLOCK


@dataclass(frozen=True)
class _LoadEndPoint(Command):
    """LOAD_RECEIVER / LOAD_SHOOTER: one end point; ``index_field`` names its row / column field."""
    shooter: ClassVar[bool]
    index_field: ClassVar[str]

    def arg(self, proto):
        index = getattr(self, self.index_field)
        return {self.index_field: index, "point": _end_point(proto, self.shooter, index, self.point)}


@dataclass(frozen=True)
class LoadReceiver(_LoadEndPoint):
    """Receiver end point of array row ``row`` := ``point`` (x, y, z); row valid."""
    row: int
    point: tuple
    op: ClassVar[Op] = Op.LOAD_RECEIVER
    member: ClassVar[str] = "load_receiver"
    shooter, index_field = False, "row"


@dataclass(frozen=True)
class LoadShooter(_LoadEndPoint):
    """Shooter sample point of array column ``col`` := ``point`` (x, y, z); column valid."""
    col: int
    point: tuple
    op: ClassVar[Op] = Op.LOAD_SHOOTER
    member: ClassVar[str] = "load_shooter"
    shooter, index_field = True, "col"


@dataclass(frozen=True)
class LoadPoints(Command):
    """Up to :data:`POINTS_PER_LOAD` loads at once: ``slots`` = ((shooter, index, (x, y, z)), ...),
    ``shooter`` False for receiver row ``index``, True for shooter column ``index``; in order (a
    later slot wins)."""
    slots: tuple
    op: ClassVar[Op] = Op.LOAD_POINTS
    member: ClassVar[str] = "load_points"

    def arg(self, proto):
        if not 1 <= len(self.slots) <= POINTS_PER_LOAD:
            raise ParameterError(f"LOAD_POINTS carries 1 to {POINTS_PER_LOAD} points, not {len(self.slots)}")
        out = [{"valid": 1, "shooter": int(bool(shooter)), "index": int(where),
                "point": _end_point(proto, shooter, int(where), point)} for shooter, where, point in self.slots]
        empty = {"valid": 0, "shooter": 0, "index": 0, "point": {"x": 0, "y": 0, "z": 0}}
        return out + [empty] * (POINTS_PER_LOAD - len(out))


@dataclass(frozen=True)
class Voxel(Command):
    """Stream voxel ``voxel``'s records to all R x S processors."""
    voxel: int
    op: ClassVar[Op] = Op.VOXEL
    member: ClassVar[str] = "voxel"

    def arg(self, proto):
        proto.check(self.voxel, proto.params.voxel_depth, "voxel", "voxel_depth")
        return {"voxel": self.voxel}


@dataclass(frozen=True)
class EndBlock(Command):
    """Close the block: one BLOCKED result."""
    op: ClassVar[Op] = Op.END_BLOCK


@dataclass(frozen=True)
class ReadCounters(Command):
    """One COUNTERS result: a snapshot covering the commands before it."""
    op: ClassVar[Op] = Op.READ_COUNTERS


@dataclass(frozen=True)
class Identify(Command):
    """One IDENTITY result: the configuration the board was built for."""
    op: ClassVar[Op] = Op.IDENTIFY


#: the command record class of each opcode
COMMANDS = {c.op: c for c in (WritePatch, WriteVoxel, BeginBlock, LoadReceiver, LoadShooter, LoadPoints,
                              Voxel, EndBlock, ReadCounters, Identify)}


@dataclass(frozen=True)
class BoardResult:
    """A decoded result: ``blocked`` (int, bit r*S + s), ``counters`` or ``identity`` (dicts)."""
    kind: ResultKind
    blocked: int = None
    counters: dict = None
    identity: dict = None


def _index_width(n):
    return max(1, ceil_log2(n))


def _nbytes(bits):
    return (bits + 7) // 8


class BoardProtocol:
    """Record layouts, the wire format and their packing for one board configuration."""

    def __init__(self, params):
        if not isinstance(params, BoardParams):
            raise ParameterError(f"board protocol needs BoardParams, not {params!r}")
        self._params = params
        self.address_width = _index_width(params.patch_depth)
        self.count_width = bits_for(params.patch_depth)
        self.voxel_width = _index_width(params.voxel_depth)
        self.row_width = _index_width(params.rows)
        self.col_width = _index_width(params.cols)
        point = point_layout(params.bits)
        self.point_slot_layout = data.StructLayout({
            "valid": unsigned(1),
            "shooter": unsigned(1),                     # 0: receiver row `index`, 1: shooter column
            "index": unsigned(max(self.row_width, self.col_width)),
            "point": point,
        })
        self.table_entry_layout = data.StructLayout({
            "start": unsigned(self.address_width),
            "count": unsigned(self.count_width),
        })
        self.arg_layout = data.UnionLayout({
            "write_patch": data.StructLayout({"address": unsigned(self.address_width),
                                              "patch": patch_layout(params.bits)}),
            "write_voxel": data.StructLayout({"voxel": unsigned(self.voxel_width),
                                              "entry": self.table_entry_layout}),
            "load_receiver": data.StructLayout({"row": unsigned(self.row_width), "point": point}),
            "load_shooter": data.StructLayout({"col": unsigned(self.col_width), "point": point}),
            "voxel": data.StructLayout({"voxel": unsigned(self.voxel_width)}),
            "load_points": data.ArrayLayout(self.point_slot_layout, POINTS_PER_LOAD),
        })
        self.command_layout = data.StructLayout({"op": Op, "arg": self.arg_layout})
        self.counters_layout = data.StructLayout({name: unsigned(COUNTER_WIDTH) for name in COUNTERS})
        self.identity_layout = data.StructLayout({name: unsigned(w) for name, w in IDENTITY_FIELDS.items()})
        self.result_layout = data.StructLayout({
            "kind": ResultKind,
            "data": data.UnionLayout({
                "blocked": unsigned(params.processors),
                "counters": self.counters_layout,
                "identity": self.identity_layout,
            }),
        })
        self._arg_offset = self.command_layout["arg"].offset
        self._kind_width = Shape.cast(ResultKind).width
        self._members = {kind: name for kind, name in zip(ResultKind, ("blocked", "counters", "identity"))}
        self._payload_bits = {}

    @property
    def params(self):
        return self._params

    def identity(self, *, rays=False, cell=Cell()):
        """The IDENTIFY result's fields for this configuration; ``rays``: of a board that makes
        its rays (version :data:`RAYS_VERSION`); ``cell``: its processor :class:`~blockray.cell.Cell`
        (the filter's format at this B)."""
        p = self._params
        return {"magic": MAGIC, "version": RAYS_VERSION if rays else VERSION, "rows": p.rows, "cols": p.cols, "bits": p.bits,
                "patch_depth": p.patch_depth, "voxel_depth": p.voxel_depth, **cell_identity(check_cell(cell).at(p.bits))}

    # -- the internal command record --------------------------------------------------------------

    def arg_bits(self, command):
        """The bits of ``command``'s ``arg`` member (0 for a command without operands)."""
        if command.member is None:
            return 0
        return pack(self.arg_layout[command.member].shape, command.arg(self))

    def record(self, command):
        """Pack one command into the board's internal command record (``command_layout``)."""
        return int(command.op) | self.arg_bits(command) << self._arg_offset

    def decode_record(self, word):
        """Unpack a command record: ``{"op": Op, "arg": {member: ...}}`` (every union member)."""
        value = unpack(self.command_layout, word)
        value["op"] = Op(value["op"])
        return value

    # -- the wire format ----------------------------------------------------------------------------

    def payload_bits(self, op, points=POINTS_PER_LOAD):
        """Payload bits of a command (``points``: LOAD_POINTS slots carried)."""
        key = (op, points)
        if key not in self._payload_bits:             # a layout's size walks it: once per command kind
            op = Op(op)
            member = COMMANDS[op].member
            self._payload_bits[key] = (points * self.point_slot_layout.size if op is Op.LOAD_POINTS
                                       else 0 if member is None else self.arg_layout[member].shape.size)
        return self._payload_bits[key]

    def command_bytes(self, op, points=POINTS_PER_LOAD):
        """Bytes of a command on the link: the header and its payload."""
        return 1 + _nbytes(self.payload_bits(op, points))

    def encode(self, command):
        """One command in the wire format (bytes)."""
        bits = self.arg_bits(command)       # checks the operands (an empty LOAD_POINTS too) first
        points = len(command.slots) if command.op is Op.LOAD_POINTS else POINTS_PER_LOAD
        header = int(command.op) | (points - 1) << 4 if command.op is Op.LOAD_POINTS else int(command.op)
        n = _nbytes(self.payload_bits(command.op, points))
        return bytes([header]) + bits.to_bytes(n, "little")

    def encode_all(self, commands):
        return b"".join(self.encode(c) for c in commands)

    def encode_blocks(self, receivers, row_off, shooters, col_off, voxels, vox_off):
        """The command stream of many block rays at once: the bytes of :meth:`encode_all` over each
        block's BEGIN_BLOCK, LOAD_POINTS (its receiver rows 0.., then its shooter columns 0..,
        :data:`POINTS_PER_LOAD` a command), VOXEL per voxel and END_BLOCK, one block after the other
        (:meth:`blockray.memory.BoardMemories.block_commands`), built with array operations (no
        Python per command). Block k's rows are ``receivers[row_off[k]:row_off[k + 1]]`` ((N, 3)
        points), its columns ``shooters[col_off[k]:col_off[k + 1]]``, its voxels
        ``voxels[vox_off[k]:vox_off[k + 1]]``."""
        p = self._params
        a = lambda x: np.asarray(x, dtype=np.int64)                             # noqa: E731
        receivers, shooters = a(receivers).reshape(-1, 3), a(shooters).reshape(-1, 3)
        row_off, col_off, vox_off = a(row_off), a(col_off), a(vox_off)
        voxels = a(voxels).reshape(-1)[vox_off[0]:vox_off[-1]]
        rows, cols, nvox = np.diff(row_off), np.diff(col_off), np.diff(vox_off)
        nblk = len(rows)
        for name, n, limit, param in (("receiver row", rows, p.rows, "rows"), ("shooter column", cols, p.cols, "cols")):
            if nblk and n.max() > limit:
                raise CapacityError(f"{name} {int(n.max()) - 1} does not fit the board ({param} {limit})")
        for name, pts in (("receiver", receivers), ("shooter", shooters)):
            bad = (pts < 0) | (pts >= 1 << p.bits)
            if bad.any():
                raise ValueError(f"a {name} point {pts[bad.any(axis=1)][0].tolist()} does not fit {p.bits} bits")
        bad = (voxels < 0) | (voxels >= p.voxel_depth)
        if bad.any():
            raise CapacityError(f"voxel {int(voxels[bad][0])} does not fit the board (voxel_depth {p.voxel_depth})")

        # one row of bytes per command (header, payload), kept up to its length: the rows in
        # stream order, flattened, are the stream
        npts = rows + cols
        loads = -(-npts // POINTS_PER_LOAD)
        ncmd = 2 + loads + nvox
        first = np.cumsum(ncmd) - ncmd                                          # each block's BEGIN_BLOCK
        vox_bytes = self.command_bytes(Op.VOXEL)
        slot_size = self.point_slot_layout.size
        width = max(self.command_bytes(Op.LOAD_POINTS), vox_bytes)
        table = np.zeros((int(ncmd.sum()), width), dtype=np.uint8)
        length = np.ones(len(table), dtype=np.int64)
        table[first, 0] = Op.BEGIN_BLOCK
        table[first + ncmd - 1, 0] = Op.END_BLOCK

        # LOAD_POINTS: slot j of a block is its row j, then its column j - rows; slot j % 4 of the
        # block's command j // 4
        blk = np.repeat(np.arange(nblk), npts)
        j = np.arange(len(blk)) - np.repeat(np.cumsum(npts) - npts, npts)
        shooter = j >= rows[blk]
        index = np.where(shooter, j - rows[blk], j)
        point = np.empty((len(j), 3), dtype=np.int64)
        point[shooter] = shooters[(col_off[blk] + index)[shooter]]
        point[~shooter] = receivers[(row_off[blk] + index)[~shooter]]
        load_first = np.cumsum(loads) - loads                                   # each block's first LOAD_POINTS
        command = load_first[blk] + j // POINTS_PER_LOAD
        place = j % POINTS_PER_LOAD
        nload = int(loads.sum())
        values = {"valid": np.ones_like(j), "shooter": shooter.astype(np.int64), "index": index,
                  ("point", "x"): point[:, 0], ("point", "y"): point[:, 1], ("point", "z"): point[:, 2]}
        columns = {}
        for path, _, _ in leaves(self.arg_layout["load_points"].shape):
            col = np.zeros(nload, dtype=np.int64)
            here = place == path[0]
            col[command[here]] = values[path[1] if len(path) == 2 else path[1:]][here]
            columns[path] = col
        payload = pack_bytes(self.arg_layout["load_points"].shape, columns) if nload else np.zeros((0, width - 1), np.uint8)
        carried = np.bincount(command, minlength=nload)                         # slots in each command
        load_rows = np.repeat(first + 1, loads) + np.arange(nload) - np.repeat(load_first, loads)
        table[load_rows, 0] = Op.LOAD_POINTS | (carried - 1) << 4
        table[load_rows, 1:1 + payload.shape[1]] = payload
        length[load_rows] = 1 + -(-carried * slot_size // 8)

        # VOXEL: the voxel number's bytes, least significant first
        vox_rows = np.repeat(first + 1 + loads, nvox) + np.arange(len(voxels)) - np.repeat(vox_off[:-1] - vox_off[0], nvox)
        table[vox_rows, 0] = Op.VOXEL
        for k in range(vox_bytes - 1):
            table[vox_rows, 1 + k] = voxels >> 8 * k & 0xFF
        length[vox_rows] = vox_bytes
        return table[np.arange(width) < length[:, None]].tobytes()

    def decode_commands(self, stream):
        """The typed commands of a wire-format byte string (the inverse of :meth:`encode_all`)."""
        out, ends = self.decode_prefix(stream)
        used = ends[-1] if ends else 0
        if used < len(stream):
            op = Op(stream[used] & 0xF)
            raise ParameterError(f"byte {used}: {op.name} needs {self.command_bytes(op, (stream[used] >> 4 & 3) + 1) - 1} "
                                 f"payload bytes, the stream ends first")
        return out

    def decode_prefix(self, stream):
        """``(commands, ends)``: the complete commands at the start of ``stream`` and the offset
        after each (a command cut off at the end is left, as a board's deframer waits for it)."""
        out, ends, i = [], [], 0
        stream = bytes(stream)
        while i < len(stream):
            header = stream[i]
            try:
                op = Op(header & 0xF)
            except ValueError:
                raise ParameterError(f"byte {i}: {header:#04x} is not a command header") from None
            points = (header >> 4 & 3) + 1
            n = _nbytes(self.payload_bits(op, points))
            if i + 1 + n > len(stream):
                break
            bits = int.from_bytes(stream[i + 1:i + 1 + n], "little")
            out.append(self._command(op, bits, points))
            i += 1 + n
            ends.append(i)
        return out, ends

    def _command(self, op, bits, points):
        cls = COMMANDS[op]
        if cls.member is None:
            return cls()
        v = unpack(self.arg_layout[cls.member].shape, bits)
        pt = lambda d: (d["x"], d["y"], d["z"])                     # noqa: E731
        if op is Op.WRITE_PATCH:
            return WritePatch(v["address"], pack(patch_layout(self._params.bits), v["patch"]))
        if op is Op.WRITE_VOXEL:
            return WriteVoxel(v["voxel"], v["entry"]["start"], v["entry"]["count"])
        if op is Op.LOAD_RECEIVER:
            return LoadReceiver(v["row"], pt(v["point"]))
        if op is Op.LOAD_SHOOTER:
            return LoadShooter(v["col"], pt(v["point"]))
        if op is Op.VOXEL:
            return Voxel(v["voxel"])
        return LoadPoints(tuple((bool(s["shooter"]), s["index"], pt(s["point"])) for s in v[:points]))

    def result_bytes(self, kind):
        """Bytes of a result of ``kind`` on the link."""
        member = self.result_layout["data"].shape[self._members[ResultKind(kind)]].shape
        return _nbytes(self._kind_width + Shape.cast(member).width)

    def result_length(self, first_byte):
        """Bytes of the result whose first byte is ``first_byte``."""
        kind = first_byte & ((1 << self._kind_width) - 1)
        try:
            return self.result_bytes(ResultKind(kind))
        except ValueError:
            raise ParameterError(f"result tag {kind} is not a result kind") from None

    def encode_result(self, result):
        """A :class:`BoardResult` as its result record (int); its wire bytes are the low
        :meth:`result_bytes` bytes."""
        member = self._members[result.kind]
        return pack(self.result_layout, {"kind": result.kind, "data": {member: getattr(result, member)}})

    def result_wire(self, result):
        return self.encode_result(result).to_bytes(self.result_bytes(result.kind), "little")

    def decode_result(self, word):
        """Unpack a result record (int or its wire bytes) into a :class:`BoardResult`."""
        if isinstance(word, (bytes, bytearray)):
            word = int.from_bytes(word, "little")
        value = unpack(self.result_layout, word)
        try:
            kind = ResultKind(value["kind"])
        except ValueError:
            raise ParameterError(f"result tag {value['kind']} is not a result kind") from None
        member = self._members[kind]
        return BoardResult(kind, **{member: value["data"][member]})

    def decode_blocked(self, data, count):
        """``count`` END_BLOCK results' wire bytes at once: ``(tags, bits)``, each result's tag
        ((count,) int) and its blocked bits ((count, R * S) bool, bit ``r * S + s`` as
        :meth:`decode_result`'s ``blocked``), without a Python loop. The bits mean something only
        where the tag is :attr:`ResultKind.BLOCKED`; the caller checks the tags."""
        n = self.result_bytes(ResultKind.BLOCKED)
        raw = np.frombuffer(bytes(data), dtype=np.uint8, count=count * n).reshape(count, n)
        tags = (raw[:, 0] & ((1 << self._kind_width) - 1)).astype(np.int64)
        bits = np.unpackbits(raw, axis=1, bitorder="little")
        lo = self.result_layout["data"].offset
        return tags, bits[:, lo:lo + self._params.processors].astype(bool)

    def reader(self):
        return ResultReader(self)

    def check(self, index, depth, what, param):
        if not 0 <= int(index) < depth:
            raise CapacityError(f"{what} {index} does not fit the board ({param} {depth})")


class ResultReader:
    """Splits a result byte stream into results: :meth:`feed` bytes, get complete results' wire
    bytes; :meth:`need` says how many more bytes complete ``n`` more results is at least."""

    def __init__(self, protocol):
        self.protocol = protocol
        self._buf = bytearray()

    def feed(self, data):
        self._buf += data
        out = []
        while self._buf:
            n = self.protocol.result_length(self._buf[0])
            if len(self._buf) < n:
                break
            out.append(bytes(self._buf[:n]))
            del self._buf[:n]
        return out

    @property
    def pending(self):
        return len(self._buf)


def fit_params(params, *, records, voxels):
    """``params`` with the smallest memories that hold a scene's partition.

    ``records``: the largest number of patch records (registrations) of any board's partition;
    ``voxels``: entries of the voxel table (v**3).
    """
    return params.with_(patch_depth=max(1, int(records)), voxel_depth=max(1, int(voxels)))


def check_capacity(params, *, records, voxels):
    """Raise :class:`CapacityError` if a partition of ``records`` records over ``voxels`` voxels
    does not fit the memories of ``params``."""
    if records > params.patch_depth:
        raise CapacityError(f"patch memory: {records} patch records (registrations) of one board's "
                            f"partition do not fit patch_depth {params.patch_depth}")
    if voxels > params.voxel_depth:
        raise CapacityError(f"voxel table: {voxels} voxels do not fit voxel_depth {params.voxel_depth}")


# -- documentation ------------------------------------------------------------------------------

def _leaf_rows(layout, prefix="", offset=0):
    if isinstance(layout, data.Layout):
        for key, field in layout:
            yield from _leaf_rows(field.shape, f"{prefix}.{key}" if prefix else str(key), offset + field.offset)
    else:
        shape = Shape.cast(layout)
        kind = "signed" if shape.signed else "unsigned"
        yield prefix, offset, shape.width, kind


def _table(layout, prefix, offset=0):
    lines = ["| field | bits | width | type |", "|---|---|---|---|"]
    for name, lo, width, kind in _leaf_rows(layout, prefix, offset):
        lines.append(f"| `{name}` | {lo + width - 1}:{lo} | {width} | {kind} |")
    return "\n".join(lines)


def describe(params):
    """Markdown tables of the wire format and the records for ``params`` (docs/board-protocol.md
    embeds the output for the default parameters; a test keeps them equal)."""
    proto = BoardProtocol(params)
    out = [f"Parameters: `{params!r}`", "",
           "Wire format: a command is its header byte (bits 3:0 `op`; LOAD_POINTS: bits 5:4 = points - 1) "
           "and the payload, the bits of its `arg` member below from bit 0 of `arg`, least significant "
           "first, zero-padded to whole bytes. A result is the low bytes of the result record "
           "(`kind`, then the member).", "",
           "| command | op | `arg` member | bytes on the link |", "|---|---|---|---|"]
    for op, cls in COMMANDS.items():
        size = (" to ".join(str(proto.command_bytes(op, n)) for n in (1, POINTS_PER_LOAD))
                if op is Op.LOAD_POINTS else str(proto.command_bytes(op)))
        out.append(f"| {cls.__name__} | {op.name} = {op.value} | "
                   f"{('`' + cls.member + '`') if cls.member else '(none)'} | {size} |")
    out += ["", "| result | `kind` | bytes on the link |", "|---|---|---|"]
    for kind in ResultKind:
        out.append(f"| `data.{proto._members[kind]}` | {kind.name} = {kind.value} | {proto.result_bytes(kind)} |")
    arg_offset = proto._arg_offset
    out += ["", f"Internal command record (the board's command register): {proto.command_layout.size} bits, "
            f"`op` in bits {Shape.cast(Op).width - 1}:0."]
    for op, cls in COMMANDS.items():
        if cls.member:
            out += ["", f"`arg.{cls.member}` ({op.name}):", "",
                    _table(proto.arg_layout[cls.member].shape, f"arg.{cls.member}", arg_offset)]
    res_offset = proto.result_layout["data"].offset
    out += ["", f"Result record: {proto.result_layout.size} bits. `kind` (bits {res_offset - 1}:0): "
            + ", ".join(f"{k.value} = {k.name}" for k in ResultKind) + ".", "",
            "`data.blocked` (END_BLOCK): bit `r * S + s` of the field is ray (shooter column s, receiver row r).", "",
            _table(proto.result_layout["data"].shape["blocked"].shape, "data.blocked", res_offset), "",
            "`data.counters` (READ_COUNTERS):", "",
            _table(proto.counters_layout, "data.counters", res_offset), "",
            f"`data.identity` (IDENTIFY; magic {MAGIC:#06x}, version {VERSION}, {RAYS_VERSION} with the block "
            f"sequencer; `cell` is the index in {', '.join(CELLS)}, and `d_bits`, `w_bits`, `w_input_bits` "
            f"the filter's mantissa widths, 0 for none):", "",
            _table(proto.identity_layout, "data.identity", res_offset)]
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    print(describe(BoardParams()), end="")

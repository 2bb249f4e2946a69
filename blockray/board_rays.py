"""The commands of rays made on the board (docs/board-protocol.md, "Rays made on the board"), in
the style of :mod:`blockray.protocol`: opcodes, typed command records, their layouts and wire
format, and the host's translation of a batch of block rays into them.

Instead of every block's points and voxels the host sends, once per render, the sample scheme
(``LOAD_SAMPLES``) and the voxel grid on the lattice (``LOAD_GRID``); then per shooter column its
record address (``COLUMN``) and the receivers' record addresses in the host's block order
(``RECEIVERS``, up to :data:`RECEIVERS_PER_COMMAND` a command, each slot flagged ``last`` at the
end of a run of at most R receivers, with each receiver's end-point weights when ``weighted``).
The board's block sequencer (the model: :mod:`blockray.sim.sequencer`) makes from them the
internal records the host sends today (BEGIN_BLOCK, LOAD_POINTS, VOXEL, END_BLOCK): a run times
each chunk of S of the K samples is one block, as ``Visibility._pair_blocks`` packs them.

The weights are :data:`WEIGHT_BITS` wide whatever the scheme (its D is their sum, at most
:data:`MAX_DENOMINATOR`), so a board is built for B and its memories only, as today, and learns D
from ``LOAD_SAMPLES``.

Wire format: a header byte (bits 3:0 the opcode, 10 to 13, after :class:`~blockray.protocol.Op`'s;
RECEIVERS: bits 5:4 = slots - 1, bit 6 = weighted), then the operands' bits, least significant
first, padded to whole bytes. LOAD_SAMPLES's operands start with K - 1 (6 bits), so its length
follows from its first payload byte.

Every patch's record address must be on the board that gets the commands: rays made on the board
need one board (P = 1) until each board holds a record of every patch.
"""

import enum
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from amaranth.hdl import unsigned
from amaranth.lib import data
from amaranth.utils import bits_for

from .errors import CapacityError, ParameterError
from .params import BoardParams, check_bits
from .protocol import BoardProtocol, Op
from .records import pack, point_layout, unpack

__all__ = ["RayOp", "RECEIVERS_PER_COMMAND", "MAX_SAMPLES", "MAX_GRID", "MAX_DENOMINATOR", "WEIGHT_BITS", "STAMP_BITS", "LoadSamples", "LoadGrid", "Column",
           "Receivers", "RAY_COMMANDS", "RayProtocol", "record_addresses", "column_commands", "describe"]


class RayOp(enum.IntEnum):
    """Opcodes of the commands of rays made on the board (bits 3:0 of the header byte)."""
    LOAD_SAMPLES = 10
    LOAD_GRID = 11
    COLUMN = 12
    RECEIVERS = 13


#: receiver slots one RECEIVERS command carries
RECEIVERS_PER_COMMAND = 4
#: the sample weight memory's depth (K <= 64, ``SampleScheme``)
MAX_SAMPLES = 64
#: voxels per axis of the lattice grid (as the host's VoxelGrid)
MAX_GRID = 256
#: the largest sample denominator D = 3 p e: p = 11 for K <= 64, the end lattice e <= 16 (``SampleScheme``)
MAX_DENOMINATOR = 3 * 11 * 16
#: bits of a weight (0 .. D)
WEIGHT_BITS = MAX_DENOMINATOR.bit_length()
#: bits of the sequencer's visited stamp per voxel: the stamps are cleared once every 2^STAMP_BITS - 1
#: blocks (and after LOAD_GRID)
STAMP_BITS = 8


@dataclass(frozen=True)
class LoadSamples:
    """The sample scheme: K weight triples, each summing to the denominator D."""
    weights: tuple
    op: ClassVar[RayOp] = RayOp.LOAD_SAMPLES


@dataclass(frozen=True)
class LoadGrid:
    """The voxel grid on the lattice: ``origin`` (x, y, z), voxel edge 2^``shift``, ``v`` per axis."""
    origin: tuple
    shift: int
    v: int
    op: ClassVar[RayOp] = RayOp.LOAD_GRID


@dataclass(frozen=True)
class Column:
    """The shooter of the blocks that follow: its record ``address`` in patch memory."""
    address: int
    op: ClassVar[RayOp] = RayOp.COLUMN


@dataclass(frozen=True)
class Receivers:
    """Receiver slots ``((address, last, weights), ...)``: ``last`` ends a run (one block per chunk
    of samples); ``weights`` (three, summing to D) the row's end point, or None for the centroid.
    A command's slots are all weighted or none is."""
    slots: tuple
    op: ClassVar[RayOp] = RayOp.RECEIVERS

    @property
    def weighted(self):
        return bool(self.slots) and self.slots[0][2] is not None


#: the command record class of each opcode
RAY_COMMANDS = {c.op: c for c in (LoadSamples, LoadGrid, Column, Receivers)}


def _nbytes(bits):
    return (bits + 7) // 8


class RayProtocol:
    """Layouts and wire format of the commands above for one board configuration ``params``; the
    board's other commands through :class:`~blockray.protocol.BoardProtocol` (``board``)."""

    def __init__(self, params):
        if isinstance(params, BoardParams):
            check_bits(params.bits)             # a board built for a B (None: not chosen yet)
        self.board = BoardProtocol(params)
        self.params = params
        weight = data.ArrayLayout(unsigned(WEIGHT_BITS), 3)
        address = unsigned(self.board.address_width)
        self.count_width = bits_for(MAX_SAMPLES - 1)
        self.weight_layout = weight
        self.grid_layout = data.StructLayout({"origin": point_layout(params.bits),
                                              "shift": unsigned(bits_for(params.bits)),
                                              "v": unsigned(bits_for(MAX_GRID))})
        self.column_layout = data.StructLayout({"address": address})
        self.slot_layout = data.StructLayout({"address": address, "last": unsigned(1)})
        self.weighted_slot_layout = data.StructLayout({"address": address, "last": unsigned(1), "weights": weight})

    # -- encoding --------------------------------------------------------------------------------

    def _check_weights(self, w, D=None):
        w = tuple(int(x) for x in w)
        if len(w) != 3 or min(w) < 0 or not 1 <= sum(w) <= MAX_DENOMINATOR or sum(w) != (D or sum(w)):
            raise ParameterError(f"a weight triple must be three integers >= 0 summing to D "
                                 f"({D or f'1 to {MAX_DENOMINATOR}'}), not {w}")
        return w

    def _operands(self, command):
        """(header byte, operand bits, operand bit count) of a command."""
        p = self.params
        if command.op is RayOp.LOAD_SAMPLES:
            k = len(command.weights)
            if not 1 <= k <= MAX_SAMPLES:
                raise ParameterError(f"LOAD_SAMPLES carries 1 to {MAX_SAMPLES} weight triples, not {k}")
            layout = data.ArrayLayout(self.weight_layout, k)
            D = sum(self._check_weights(command.weights[0]))
            bits = pack(layout, [list(self._check_weights(w, D)) for w in command.weights])
            return int(command.op), (k - 1) | bits << self.count_width, self.count_width + layout.size
        if command.op is RayOp.LOAD_GRID:
            if not 0 <= command.shift <= p.bits or not 1 <= command.v <= MAX_GRID or command.v ** 3 > p.voxel_depth:
                raise CapacityError(f"grid of {command.v}^3 voxels of edge 2^{command.shift} does not fit the board "
                                    f"(B {p.bits}, voxel_depth {p.voxel_depth})")
            value = {"origin": dict(zip("xyz", map(int, command.origin))), "shift": command.shift, "v": command.v}
            return int(command.op), pack(self.grid_layout, value), self.grid_layout.size
        if command.op is RayOp.COLUMN:
            self.board.check(command.address, p.patch_depth, "patch address", "patch_depth")
            return int(command.op), command.address, self.column_layout.size
        return self._receivers(command)

    def _receivers(self, command):
        n = len(command.slots)
        if not 1 <= n <= RECEIVERS_PER_COMMAND:
            raise ParameterError(f"RECEIVERS carries 1 to {RECEIVERS_PER_COMMAND} slots, not {n}")
        weighted = command.weighted
        layout = self.weighted_slot_layout if weighted else self.slot_layout
        values = []
        for address, last, w in command.slots:
            if (w is not None) != weighted:
                raise ParameterError("a RECEIVERS command's slots are all weighted or none is")
            self.board.check(address, self.params.patch_depth, "patch address", "patch_depth")
            values.append({"address": int(address), "last": int(bool(last))}
                          | ({"weights": list(self._check_weights(w))} if weighted else {}))
        header = int(command.op) | (n - 1) << 4 | int(weighted) << 6
        array = data.ArrayLayout(layout, n)
        return header, pack(array, values), array.size

    def encode(self, command):
        """One command in the wire format (bytes): a command of this module or of
        :mod:`blockray.protocol`."""
        if not isinstance(command.op, RayOp):
            return self.board.encode(command)
        header, bits, size = self._operands(command)
        return bytes([header]) + bits.to_bytes(_nbytes(size), "little")

    def encode_all(self, commands):
        return b"".join(self.encode(c) for c in commands)

    def command_bytes(self, op, slots=RECEIVERS_PER_COMMAND, *, weighted=False, samples=MAX_SAMPLES):
        """Bytes of a command on the link (RECEIVERS: of ``slots`` slots; LOAD_SAMPLES: of K = ``samples``)."""
        if op in Op.__members__.values():
            return self.board.command_bytes(op)
        op = RayOp(op)
        if op is RayOp.LOAD_SAMPLES:
            return 1 + _nbytes(self.count_width + samples * self.weight_layout.size)
        if op is RayOp.RECEIVERS:
            layout = self.weighted_slot_layout if weighted else self.slot_layout
            return 1 + _nbytes(slots * layout.size)
        return 1 + _nbytes((self.grid_layout if op is RayOp.LOAD_GRID else self.column_layout).size)

    # -- decoding --------------------------------------------------------------------------------

    def decode_commands(self, stream):
        """The typed commands of a wire-format byte string holding commands of both modules."""
        out, ends = self.decode_prefix(stream)
        if (ends[-1] if ends else 0) < len(stream):
            raise ParameterError(f"byte {ends[-1] if ends else 0}: a command is cut off by the stream's end")
        return out

    def decode_prefix(self, stream):
        """``(commands, ends)``: the complete commands at the start of ``stream`` and the offset
        after each (a command cut off at the end is left for more bytes)."""
        stream, out, ends, i = bytes(stream), [], [], 0
        while i < len(stream):
            header = stream[i]
            if header & 0xF not in RAY_COMMANDS:             # one of blockray.protocol's
                try:
                    n = self.board.command_bytes(Op(header & 0xF), (header >> 4 & 3) + 1)
                except ValueError:
                    raise ParameterError(f"byte {i}: {header:#04x} is not a command header") from None
                if i + n > len(stream):
                    break
                out += self.board.decode_commands(stream[i:i + n])
                i += n
                ends.append(i)
                continue
            op = RayOp(header & 0xF)
            weighted, slots = bool(header >> 6 & 1), (header >> 4 & 3) + 1
            if op is RayOp.LOAD_SAMPLES and i + 1 == len(stream):
                break                                       # its length is in its first payload byte
            samples = stream[i + 1] % (1 << self.count_width) + 1 if op is RayOp.LOAD_SAMPLES else 1
            n = self.command_bytes(op, slots, weighted=weighted, samples=samples)
            if i + n > len(stream):
                break
            out.append(self._command(op, int.from_bytes(stream[i + 1:i + n], "little"), slots, weighted, samples))
            i += n
            ends.append(i)
        return out, ends

    def _command(self, op, bits, slots, weighted, samples):
        if op is RayOp.LOAD_SAMPLES:
            w = unpack(data.ArrayLayout(self.weight_layout, samples), bits >> self.count_width)
            return LoadSamples(tuple(tuple(t) for t in w))
        if op is RayOp.LOAD_GRID:
            v = unpack(self.grid_layout, bits)
            return LoadGrid(tuple(v["origin"][c] for c in "xyz"), v["shift"], v["v"])
        if op is RayOp.COLUMN:
            return Column(bits)
        layout = self.weighted_slot_layout if weighted else self.slot_layout
        values = unpack(data.ArrayLayout(layout, slots), bits)
        return Receivers(tuple((s["address"], bool(s["last"]), tuple(s["weights"]) if weighted else None)
                               for s in values))


def record_addresses(patch_of_word, patches):
    """(patches,) int64: the first patch-memory word holding each patch's record (-1: none)."""
    address = np.full(patches, -1, dtype=np.int64)
    words = np.asarray(patch_of_word, dtype=np.int64)
    first = np.unique(words, return_index=True)
    address[first[0]] = first[1]
    return address


def column_commands(batch, address, samples, cols):
    """The COLUMN and RECEIVERS commands that make ``batch`` (a :class:`~blockray.board.BlockBatch`)
    on the board: each run of receivers must be followed by its blocks for every chunk of
    ``cols`` of the ``samples`` samples, in order, as ``Visibility._pair_blocks`` packs them.
    ``address``: each patch's record address (:func:`record_addresses`)."""
    chunks = -(-samples // cols)
    out, slots, column = [], [], None
    for b in range(0, len(batch), chunks):
        if not _is_run(batch, b, samples, cols):
            raise ParameterError(f"block {b}: not a run of receivers times every chunk of {cols} of the "
                                 f"{samples} samples (the order the board makes blocks in)")
        if batch.shooter_patch[batch.col_off[b]] != column:
            out += _flush(slots)
            column = int(batch.shooter_patch[batch.col_off[b]])
            out.append(Column(_address(address, column)))
        run = range(batch.row_off[b], batch.row_off[b + 1])
        for r in run:
            w = None if batch.receiver_weights is None else tuple(int(x) for x in batch.receiver_weights[r])
            slots.append((_address(address, int(batch.receiver_patch[r])), r == run[-1], w))
    return out + _flush(slots)


def _is_run(batch, b, samples, cols):
    """Blocks b, b + 1, ...: one run of receivers (the same rows, at least one, the same end points
    and shooter) times each chunk of ``cols`` of the ``samples`` samples, in order."""
    end = b + -(-samples // cols)
    if end > len(batch):
        return False
    cs = slice(batch.col_off[b], batch.col_off[end])
    rows = [slice(batch.row_off[k], batch.row_off[k + 1]) for k in range(b, end)]

    def same(a):
        return a is None or all(np.array_equal(a[r], a[rows[0]]) for r in rows)
    return (batch.row_off[b + 1] > batch.row_off[b] and np.array_equal(batch.shooter_sample[cs], np.arange(samples))
            and np.array_equal(np.diff(batch.col_off[b:end + 1]), np.minimum(cols, samples - np.arange(0, samples, cols)))
            and (batch.shooter_patch[cs] == batch.shooter_patch[batch.col_off[b]]).all()
            and same(batch.receiver_patch) and same(batch.receiver_weights))


def _address(address, patch):
    if address[patch] < 0:
        raise CapacityError(f"patch {patch} has no record on the board: rays made on the board need every "
                            f"patch on the board that gets the commands (one board)")
    return int(address[patch])


def _flush(slots):
    """The RECEIVERS commands of the pending ``slots`` (emptied)."""
    out = [Receivers(tuple(slots[i:i + RECEIVERS_PER_COMMAND])) for i in range(0, len(slots), RECEIVERS_PER_COMMAND)]
    slots.clear()
    return out


def describe(params):
    """Markdown: the commands of rays made on the board, their operands and bytes for ``params``
    (docs/board-protocol.md, "Rays made on the board")."""
    proto = RayProtocol(params)
    a, w = proto.board.address_width, WEIGHT_BITS
    rows = [("LOAD_SAMPLES", f"K - 1 ({proto.count_width} bits), K weight triples (3 x {w} bits each)",
             f"{proto.command_bytes(RayOp.LOAD_SAMPLES, samples=1)} to {proto.command_bytes(RayOp.LOAD_SAMPLES)}"),
            ("LOAD_GRID", "origin (3 x B bits), shift e (edge 2^e), v (voxels per axis)",
             str(proto.command_bytes(RayOp.LOAD_GRID))),
            ("COLUMN", f"the shooter's record address ({a} bits)", str(proto.command_bytes(RayOp.COLUMN))),
            ("RECEIVERS", f"1 to {RECEIVERS_PER_COMMAND} slots (header bits 5:4 = slots - 1): address ({a} bits), "
                          f"last (1); with header bit 6 (weighted) the end point's weights (3 x {w} bits)",
             " to ".join(str(proto.command_bytes(RayOp.RECEIVERS, n)) for n in (1, RECEIVERS_PER_COMMAND))
             + " (weighted " + " to ".join(str(proto.command_bytes(RayOp.RECEIVERS, n, weighted=True))
                                         for n in (1, RECEIVERS_PER_COMMAND)) + ")")]
    out = [f"Parameters: `{params!r}`", "",
           "| command | op | operands | bytes on the link |", "|---|---|---|---|"]
    out += [f"| {name} | {RayOp[name].value} | {ops} | {n} |" for name, ops, n in rows]
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    from .params import BoardParams
    print(describe(BoardParams()), end="")

"""The block sequencer: rays made on the board in gateware (docs/board-protocol.md, "Rays made on
the board: design" and "The sequencer's cycles"; its bit-exact model, cycles included, is
:class:`blockray.sim.sequencer.BlockSequencer`). Not wired into the board yet.

::

    items --> weights, grid --> column's K points, a run's end points (PointUnit) --> point memory
                                                                                      |
    records <-- BEGIN_BLOCK, LOAD_POINTS, VOXEL (RayWalker boxes, visited stamps), END_BLOCK

Command items (:func:`item_layout`; :func:`command_items` splits the commands of
:mod:`blockray.board_rays` into them): a weight triple, the grid, the column, one receiver slot.
Records: the board's internal command records (:attr:`~blockray.protocol.BoardProtocol.command_layout`),
the same bits as :meth:`~blockray.protocol.BoardProtocol.record` of the model's. Patch records
and voxel-table entries are read through two memory read ports the board's memories give.

One thing at a time, each record offered in the cycle the model says (a cycle counts unless the
sequencer waits for an item, ``commands.ready`` and no ``valid``, or for its record to be taken).
The visited bits are stamps: a block's tag, the memory cleared to 0 when the tag would wrap.
"""

import enum

from amaranth.hdl import Module, Mux, Signal, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.memory import Memory, ReadPort
from amaranth.lib.wiring import In, Out
from amaranth.utils import bits_for

from ..board_rays import MAX_SAMPLES, STAMP_BITS, WEIGHT_BITS, Column, LoadGrid, LoadSamples, RayProtocol, Receivers
from ..errors import ParameterError
from ..params import BoardParams
from ..protocol import POINTS_PER_LOAD, BoardProtocol, Op
from ..records import patch_layout, point_layout
from .points import PointUnit
from .ray_walk import RayWalker, box_layout

__all__ = ["BlockSequencer", "ItemOp", "item_layout", "command_items"]


class ItemOp(enum.IntEnum):
    """What a command item is."""
    SAMPLE = 0      # LOAD_SAMPLES' weight triple ``index`` (0 sets D)
    GRID = 1        # LOAD_GRID
    COLUMN = 2      # COLUMN: the shooter's record address
    RECEIVER = 3    # one RECEIVERS slot


def item_layout(rays):
    """A command item for :class:`~blockray.board_rays.RayProtocol` ``rays``."""
    weights = rays.weight_layout
    address = rays.column_layout["address"].shape
    return data.StructLayout({"op": ItemOp, "arg": data.UnionLayout({
        "sample": data.StructLayout({"index": unsigned(rays.count_width), "weights": weights}),
        "grid": rays.grid_layout,
        "column": rays.column_layout,
        "receiver": data.StructLayout({"address": address, "last": unsigned(1), "weighted": unsigned(1),
                                       "weights": weights})})})


def command_items(rays, command):
    """The items (``item_layout(rays).const``) of a command of :mod:`blockray.board_rays`."""
    layout = item_layout(rays)

    def item(op, member, value):
        return layout.const({"op": op, "arg": {member: value}})
    if isinstance(command, LoadSamples):
        return [item(ItemOp.SAMPLE, "sample", {"index": k, "weights": list(w)}) for k, w in enumerate(command.weights)]
    if isinstance(command, LoadGrid):
        return [item(ItemOp.GRID, "grid", {"origin": dict(zip("xyz", command.origin)), "shift": command.shift,
                                           "v": command.v})]
    if isinstance(command, Column):
        return [item(ItemOp.COLUMN, "column", {"address": command.address})]
    if isinstance(command, Receivers):
        return [item(ItemOp.RECEIVER, "receiver", {"address": a, "last": int(last), "weighted": int(w is not None),
                                                   "weights": list(w or (0, 0, 0))})
                for a, last, w in command.slots]
    raise ParameterError(f"not a command of rays made on the board: {command!r}")


class BlockSequencer(wiring.Component):
    """``commands`` (In, :func:`item_layout`) -> ``records`` (Out, the board's command records).

    Parameters: ``params`` (:class:`~blockray.params.BoardParams`: B, R, S, the memory depths),
    ``stamp_bits`` (the visited stamps' width, at least 2).

    Ports
    ``patch_read``  a read port of patch memory (packed :func:`~blockray.records.patch_layout`).
    ``table_read``  a read port of the voxel table (``table_entry_layout``).
    """

    def __init__(self, params, *, stamp_bits=STAMP_BITS):
        self._MustUse__silence = True       # no "created but never used" warning on a rejected parameter
        if not isinstance(params, BoardParams):
            raise ParameterError(f"block sequencer needs BoardParams, not {params!r}")
        if isinstance(stamp_bits, bool) or not isinstance(stamp_bits, int) or stamp_bits < 2:
            raise ParameterError(f"stamp_bits must be an integer of at least 2, not {stamp_bits!r}",
                                 parameter="stamp_bits")
        self._params, self._stamp_bits = params, stamp_bits
        self._rays = RayProtocol(params)    # checks B
        proto = self._proto = BoardProtocol(params)
        super().__init__({
            "commands": In(stream.Signature(item_layout(self._rays))),
            "records": Out(stream.Signature(proto.command_layout)),
            "patch_read": In(ReadPort.Signature(addr_width=proto.address_width,
                                                shape=unsigned(patch_layout(params.bits).size))),
            "table_read": In(ReadPort.Signature(addr_width=proto.voxel_width, shape=proto.table_entry_layout)),
        })
        self._MustUse__silence = False

    @property
    def params(self):
        return self._params

    @property
    def stamp_bits(self):
        return self._stamp_bits

    def elaborate(self, platform):
        m = Module()
        s = self._state(m)
        with m.FSM(init="Idle"):
            self._take(m, s)
            self._inverse(m, s)
            self._points(m, s)
            self._load(m, s)
            self._walk(m, s)
        return m

    def _state(self, m):
        """Registers, memories and units, as a namespace."""
        p, B = self._params, self._params.bits
        s = _Namespace()
        s.K, s.k, s.n = Signal(range(MAX_SAMPLES + 1)), Signal(range(MAX_SAMPLES)), Signal(range(p.rows + 1))
        s.shift, s.odd, s.third = Signal(range(WEIGHT_BITS)), Signal(WEIGHT_BITS), Signal(WEIGHT_BITS)
        s.inverse, s.product, s.bit = Signal(B), Signal(B), Signal(range(B + 1))
        s.grid = Signal(self._rays.grid_layout)
        s.tag, s.clear = Signal(self._stamp_bits), Signal(self._proto.voxel_width + 1)
        s.column, s.receiver = Signal(self._rays.column_layout), Signal(item_layout(self._rays)["arg"].shape["receiver"].shape)
        s.on_column = Signal()                                  # the point unit works for the column
        s.c0, s.j, s.r, s.c = (Signal(range(MAX_SAMPLES + p.rows + 1), name=n) for n in ("c0", "j", "r", "c"))
        s.slots = Signal(data.ArrayLayout(self._proto.point_slot_layout, POINTS_PER_LOAD))
        s.box = Signal(box_layout())
        s.at = Signal(box_layout()["lo"].shape)                # the box's voxel being read
        s.voxel = Signal(self._proto.voxel_width)
        s.read_at = Signal(box_layout()["lo"].shape)           # the voxel whose entry and stamp are read
        v = s.grid.v
        s.index = (s.read_at[0] * v + s.read_at[1]) * v + s.read_at[2]
        m.submodules.weights = wm = Memory(shape=self._rays.weight_layout, depth=MAX_SAMPLES, init=[])
        m.submodules.points = pm = Memory(shape=point_layout(B), depth=MAX_SAMPLES + p.rows, init=[])
        m.submodules.stamps = sm = Memory(shape=unsigned(self._stamp_bits), depth=p.voxel_depth, init=[])
        s.w_write, s.w_read = wm.write_port(), wm.read_port()
        s.p_write, s.p_read, s.q_read = pm.write_port(), pm.read_port(), pm.read_port()
        s.s_write, s.s_read = sm.write_port(), sm.read_port()
        for port in (s.w_read, s.p_read, s.q_read, s.s_read, self.patch_read, self.table_read):
            m.d.comb += port.en.eq(0)                           # each state that reads enables its ports
        m.submodules.point_unit = s.unit = PointUnit(bits=B)
        m.submodules.ray_walker = s.walker = RayWalker(bits=B)
        m.d.comb += [s.unit.shift.eq(s.shift), s.unit.inverse.eq(s.inverse)]
        s.S_b = Mux(s.K - s.c0 < p.cols, s.K - s.c0, p.cols)   # the chunk's samples
        s.points = s.n + s.S_b                                  # a block's points to load
        return s

    def _take(self, m, s):
        """Idle: take an item; a weight triple and the grid are stored at once."""
        item = self.commands.payload
        with m.State("Idle"):
            m.d.comb += self.commands.ready.eq(1)
            with m.If(self.commands.valid):
                with m.Switch(item.op):
                    with m.Case(ItemOp.SAMPLE):
                        self._sample(m, s, item.arg.sample)
                    with m.Case(ItemOp.GRID):
                        m.d.sync += [s.grid.eq(item.arg.grid), s.tag.eq(0)]     # stamps of another grid
                    with m.Case(ItemOp.COLUMN):
                        m.d.sync += [s.column.eq(item.arg.column), s.k.eq(0), s.on_column.eq(1)]
                        m.next = "Fetch"
                    with m.Case(ItemOp.RECEIVER):
                        r = item.arg.receiver
                        m.d.sync += [s.receiver.eq(r), s.on_column.eq(0)]
                        with m.If(~r.weighted):                 # the centroid
                            m.d.sync += [s.receiver.weights[i].eq(s.third) for i in range(3)]
                        m.next = "Fetch"

    def _sample(self, m, s, sample):
        """A weight triple; the first sets D = d 2^e: e, d, D / 3, and starts d^-1."""
        m.d.comb += [s.w_write.addr.eq(sample.index), s.w_write.data.eq(sample.weights), s.w_write.en.eq(1)]
        m.d.sync += s.K.eq(sample.index + 1)
        with m.If(sample.index == 0):
            D = sample.weights[0] + sample.weights[1] + sample.weights[2]
            e = Signal(range(WEIGHT_BITS))
            for b in reversed(range(WEIGHT_BITS)):              # the lowest set bit wins
                with m.If(D.bit_select(b, 1)):
                    m.d.comb += e.eq(b)
            d = (D >> e)[:WEIGHT_BITS]
            m.d.sync += [s.shift.eq(e), s.odd.eq(d), s.third.eq((D * 683) >> 11),     # exact for 3 | D < 6144
                         s.inverse.eq(1), s.product.eq(d), s.bit.eq(1)]
            m.next = "Inverse"

    def _inverse(self, m, s):
        """d^-1 mod 2^B a bit a cycle: product = d inverse = 1 mod 2^bit; a set bit is cleared by
        adding d 2^bit, which sets that bit of the inverse."""
        with m.State("Inverse"):
            with m.If(s.product.bit_select(s.bit, 1)):
                m.d.sync += [s.inverse.eq(s.inverse | (1 << s.bit)), s.product.eq(s.product + (s.odd << s.bit))]
            m.d.sync += s.bit.eq(s.bit + 1)
            with m.If(s.bit == self._params.bits - 1):
                m.next = "Idle"

    def _points(self, m, s):
        """A point: the record and weights read, the job given, the point stored (15 cycles)."""
        unit, rows = s.unit, MAX_SAMPLES
        with m.State("Fetch"):
            m.d.comb += [self.patch_read.addr.eq(Mux(s.on_column, s.column.address, s.receiver.address)),
                         self.patch_read.en.eq(1), s.w_read.addr.eq(s.k), s.w_read.en.eq(1)]
            m.next = "Job"
        with m.State("Job"):
            m.d.comb += [unit.jobs.valid.eq(1), unit.jobs.payload.patch.eq(self.patch_read.data),
                         unit.jobs.payload.weights.eq(Mux(s.on_column, s.w_read.data, s.receiver.weights))]
            with m.If(unit.jobs.ready):
                m.next = "Wait"
        with m.State("Wait"):
            m.d.comb += [unit.points.ready.eq(1), s.p_write.data.eq(unit.points.payload),
                         s.p_write.addr.eq(Mux(s.on_column, s.k, rows + s.n)), s.p_write.en.eq(unit.points.valid)]
            with m.If(unit.points.valid):
                with m.If(s.on_column):
                    m.d.sync += s.k.eq(s.k + 1)
                    m.next = "Fetch"
                    with m.If(s.k == s.K - 1):
                        m.next = "Idle"
                with m.Else():
                    m.d.sync += s.n.eq(s.n + 1)
                    m.next = "Idle"
                    with m.If(s.receiver.last):
                        m.d.sync += s.c0.eq(0)
                        self._block(m, s)

    def _block(self, m, s):
        """Start a block: a new tag, the stamps cleared first when it would wrap."""
        with m.If((s.tag == 0) | (s.tag == (1 << self._stamp_bits) - 1)):
            m.d.sync += [s.tag.eq(1), s.clear.eq(0)]
            m.next = "Clear"
        with m.Else():
            m.d.sync += s.tag.eq(s.tag + 1)
            m.next = "Begin"

    def _offer(self, m, op, then):
        """Offer a record of ``op`` in this state; to state ``then`` once it is taken."""
        m.d.comb += [self.records.valid.eq(1), self.records.payload.op.eq(op)]
        with m.If(self.records.ready):
            m.next = then

    def _load(self, m, s):
        """Clear, BEGIN_BLOCK and the LOAD_POINTS: rows 0.. then the chunk's columns, 2 cycles a point."""
        v = s.grid.v
        with m.State("Clear"):
            m.d.comb += [s.s_write.addr.eq(s.clear), s.s_write.data.eq(0), s.s_write.en.eq(1)]
            m.d.sync += s.clear.eq(s.clear + 1)
            with m.If(s.clear == v * v * v - 1):
                m.next = "Begin"
        with m.State("Begin"):
            self._offer(m, Op.BEGIN_BLOCK, "Gather")
            m.d.sync += [s.j.eq(0), s.slots.eq(0)]
        row = s.j < s.n
        with m.State("Gather"):
            m.d.comb += [s.p_read.addr.eq(Mux(row, MAX_SAMPLES + s.j, s.c0 + s.j - s.n)), s.p_read.en.eq(1)]
            m.next = "Place"
        with m.State("Place"):
            for i in range(POINTS_PER_LOAD):
                with m.If(s.j[:2] == i):
                    slot = s.slots[i]
                    m.d.sync += [slot.valid.eq(1), slot.shooter.eq(~row), slot.point.eq(s.p_read.data),
                                 slot.index.eq(Mux(row, s.j, s.j - s.n))]
            m.d.sync += s.j.eq(s.j + 1)
            m.next = "Gather"
            with m.If((s.j[:2] == POINTS_PER_LOAD - 1) | (s.j == s.points - 1)):
                m.next = "Load"
        with m.State("Load"):
            m.d.comb += self.records.payload.arg.load_points.eq(s.slots)
            with m.If(s.j == s.points):
                self._offer(m, Op.LOAD_POINTS, "RayFetch")
                m.d.sync += [s.r.eq(0), s.c.eq(0)]
            with m.Else():
                self._offer(m, Op.LOAD_POINTS, "Gather")
            with m.If(self.records.ready):
                m.d.sync += s.slots.eq(0)

    def _walk(self, m, s):
        """Each ray (row r outer, column c inner) walked; each box's voxels read and decided; END_BLOCK."""
        walker, v = s.walker, s.grid.v
        with m.State("RayFetch"):
            m.d.comb += [s.p_read.addr.eq(s.c0 + s.c), s.q_read.addr.eq(MAX_SAMPLES + s.r),
                         s.p_read.en.eq(1), s.q_read.en.eq(1)]
            m.next = "RayJob"
        with m.State("RayJob"):
            job = walker.jobs.payload
            m.d.comb += [walker.jobs.valid.eq(1), job.p.eq(s.p_read.data), job.q.eq(s.q_read.data),
                         job.origin.eq(s.grid.origin), job.shift.eq(s.grid.shift), job.v.eq(v)]
            with m.If(walker.jobs.ready):
                m.next = "Box"
        with m.State("Box"):
            box = walker.boxes.payload
            m.d.comb += walker.boxes.ready.eq(1)
            with m.If(walker.boxes.valid):
                m.d.sync += [s.box.eq(box), s.at.eq(box.lo)]
                with m.If(~box.empty):
                    self._read(m, s, box.lo)
                    m.next = "Voxel"
                with m.Elif(box.last):
                    self._next_ray(m, s)
        with m.State("Voxel"):
            self._decide(m, s)
        with m.State("End"):
            self._offer(m, Op.END_BLOCK, "Idle")
            with m.If(self.records.ready):
                m.d.sync += s.c0.eq(s.c0 + self._params.cols)
                with m.If(s.c0 + self._params.cols < s.K):
                    self._block(m, s)
                with m.Else():
                    m.d.sync += s.n.eq(0)

    def _read(self, m, s, at):
        """Read voxel ``at``'s table entry and stamp, to be decided in the next cycle."""
        m.d.comb += [s.read_at.eq(at), self.table_read.addr.eq(s.index), s.s_read.addr.eq(s.index),
                     self.table_read.en.eq(1), s.s_read.en.eq(1)]
        m.d.sync += s.voxel.eq(s.index)

    def _decide(self, m, s):
        """A voxel a cycle: stamped if new, its VOXEL offered if new and not empty, while the box's
        next voxel (x outer, z inner) is read; after the last, the next box or ray. Waiting for
        the record to be taken, the read ports hold the voxel's entry and stamp."""
        new = s.s_read.data != s.tag
        offer = new & (self.table_read.data.count != 0)
        m.d.comb += [self.records.valid.eq(offer), self.records.payload.op.eq(Op.VOXEL),
                     self.records.payload.arg.voxel.voxel.eq(s.voxel)]
        at, lo, hi = s.at, s.box.lo, s.box.hi
        following = Signal.like(at)
        m.d.comb += following.eq(at)
        with m.If(at[2] != hi[2]):
            m.d.comb += following[2].eq(at[2] + 1)
        with m.Elif(at[1] != hi[1]):
            m.d.comb += [following[1].eq(at[1] + 1), following[2].eq(lo[2])]
        with m.Else():
            m.d.comb += [following[0].eq(at[0] + 1), following[1].eq(lo[1]), following[2].eq(lo[2])]
        with m.If(~offer | self.records.ready):
            m.d.comb += [s.s_write.addr.eq(s.voxel), s.s_write.data.eq(s.tag), s.s_write.en.eq(new)]
            with m.If((at[2] != hi[2]) | (at[1] != hi[1]) | (at[0] != hi[0])):
                m.d.sync += at.eq(following)
                self._read(m, s, following)
            with m.Elif(s.box.last):
                self._next_ray(m, s)
            with m.Else():
                m.next = "Box"

    def _next_ray(self, m, s):
        m.next = "RayFetch"
        with m.If(s.c != s.S_b - 1):
            m.d.sync += s.c.eq(s.c + 1)
        with m.Elif(s.r != s.n - 1):
            m.d.sync += [s.c.eq(0), s.r.eq(s.r + 1)]
        with m.Else():
            m.next = "End"


class _Namespace:
    """The sequencer's signals, passed between the elaborate helpers."""

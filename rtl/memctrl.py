"""The voxel-to-patch memory controller: voxel numbers in, the voxels' patch records out.

Board memory holds this board's partition of the patch records in voxel order (a patch
registered in k voxels occupies k words) and a voxel table of ``(start, count)`` per voxel. Given
a stream of voxel numbers, the controller streams each voxel's records ``start .. start+count-1``
to the processor array, one per cycle.

Structure (one slot, no bubbles between voxels)::

    voxels --accept--> voxel table read (sync) --> issue: address = start, start+1, ...
                                                       |
                                                       v
                       patch memory read (sync) --> broadcast register --> records

A voxel is accepted in the cycle its predecessor issues its last record (or while the slot is
empty): its table entry is read in that cycle, so its first record issues the next cycle. A voxel
therefore occupies the issue slot for exactly ``max(1, count)`` cycles (an empty voxel costs one
bubble), and consecutive voxels stream without gaps as long as the next voxel number is offered
in time. ``voxels.ready`` depends on the controller's state only (never on ``voxels.valid``).

Latency :attr:`latency` = 2 cycles from a record's issue (``issue`` high) to the record on
``records`` (memory read + broadcast register). Throughput one record per cycle. ``records``
never stalls (the array is fully pipelined), so it has no ``ready``.

The voxel table's read port is transparent to its write port, so a WRITE_VOXEL followed at once by
a VOXEL of the same voxel reads the new entry.
"""

from amaranth.hdl import Module, Mux, Signal, unsigned
from amaranth.lib import stream, wiring
from amaranth.lib.memory import Memory, ReadPort
from amaranth.lib.wiring import In, Out

from ..errors import ParameterError
from ..params import BoardParams
from ..records import patch_layout
from ..protocol import BoardProtocol

__all__ = ["MemoryController"]


class MemoryController(wiring.Component):
    """Patch memory, voxel table and the record streamer of one board.

    Parameters: ``params`` (:class:`~blockray.params.BoardParams`: ``bits``, ``patch_depth``,
    ``voxel_depth``); ``patch_init`` / ``table_init`` optional initial contents (lists of packed
    records as ints / ``{"start", "count"}`` dicts), for tests.

    Ports
    ``voxels``       In stream of voxel numbers (``voxel_width`` bits).
    ``records``      Out stream (always ready) of patch records (:func:`~blockray.records.patch_layout`).
    ``patch_write``  In stream (always ready) of ``{address, patch}``: one word per cycle.
    ``table_write``  In stream (always ready) of ``{voxel, entry: {start, count}}``.
    ``issue``        Out: a record issues this cycle (it reaches ``records`` :attr:`latency` later).
    ``step``         Out: the issue slot does one cycle of voxel work (a record or an empty voxel's
                     bubble). The board counts these as VOXEL cycles.
    ``free``         Out: the slot can take a voxel this cycle: it is empty or does its voxel's
                     last step (the same as ``voxels.ready``).
    ``enable``       In (default 1): the slot may advance this cycle. A board with the filtered
                     cell lowers it when its array has no credit (the broadcast stalls).
    ``rays_patch``, ``rays_table``  with ``rays``: a second read port of each memory, the block
                     sequencer's (rays made on the board; the table's transparent to its writes).
    ``exact_patch``, ``record_address``  with ``exact_read``: another read port of the patch
                     memory, the lean array's shared exact unit's (it re-reads the record of an
                     undecided test), and the patch address of the record on ``records``.
    """

    def __init__(self, params, *, patch_init=(), table_init=(), rays=False, exact_read=False):
        self._MustUse__silence = True       # no "created but never used" warning on a rejected parameter
        if not isinstance(params, BoardParams):
            raise ParameterError(f"memory controller needs BoardParams, not {params!r}")
        self._params = params
        self._protocol = proto = BoardProtocol(params)
        self._patch_init = list(patch_init)
        self._table_init = list(table_init)
        if len(self._patch_init) > params.patch_depth:
            raise ParameterError(f"patch_init has {len(self._patch_init)} words, more than patch_depth "
                                 f"{params.patch_depth}")
        if len(self._table_init) > params.voxel_depth:
            raise ParameterError(f"table_init has {len(self._table_init)} entries, more than voxel_depth "
                                 f"{params.voxel_depth}")
        args = proto.arg_layout
        super().__init__({
            "voxels": In(stream.Signature(unsigned(proto.voxel_width))),
            "records": Out(stream.Signature(patch_layout(params.bits), always_ready=True)),
            "patch_write": In(stream.Signature(args["write_patch"].shape, always_ready=True)),
            "table_write": In(stream.Signature(args["write_voxel"].shape, always_ready=True)),
            "issue": Out(1),
            "step": Out(1),
            "free": Out(1),
            "enable": In(1, init=1),
        } | ({"rays_patch": Out(self._patch_port()),
              "rays_table": Out(ReadPort.Signature(addr_width=proto.voxel_width, shape=proto.table_entry_layout))}
             if rays else {})
           | ({"exact_patch": Out(self._patch_port()), "record_address": Out(proto.address_width)}
              if exact_read else {}))
        self._rays, self._exact_read = rays, exact_read
        self._MustUse__silence = False

    def _patch_port(self):
        return ReadPort.Signature(addr_width=self._protocol.address_width,
                                  shape=unsigned(patch_layout(self._params.bits).size))

    @property
    def params(self):
        return self._params

    @property
    def protocol(self):
        return self._protocol

    #: cycles from a record's issue to its appearance on ``records``
    latency = 2

    def elaborate(self, platform):
        m = Module()
        p, proto = self._params, self._protocol

        # raw words (packed patch records): initialised from packed ints
        m.submodules.patches = patches = Memory(
            shape=unsigned(patch_layout(p.bits).size), depth=p.patch_depth, init=self._patch_init)
        m.submodules.table = table = Memory(
            shape=proto.table_entry_layout, depth=p.voxel_depth, init=self._table_init)
        patch_w = patches.write_port()
        patch_r = patches.read_port()
        table_w = table.write_port()
        table_r = table.read_port(transparent_for=(table_w,))
        extra = []
        if self._rays:
            extra += [(self.rays_patch, patches.read_port()),
                      (self.rays_table, table.read_port(transparent_for=(table_w,)))]
        if self._exact_read:
            extra.append((self.exact_patch, patches.read_port()))
        for port, memory_port in extra:
            # assigned, not connected: a memory of one entry has 0 address bits, the protocol's 1
            m.d.comb += [memory_port.addr.eq(port.addr), memory_port.en.eq(port.en), port.data.eq(memory_port.data)]

        m.d.comb += [
            patch_w.addr.eq(self.patch_write.payload.address),
            patch_w.data.eq(self.patch_write.payload.patch),
            patch_w.en.eq(self.patch_write.valid),
            table_w.addr.eq(self.table_write.payload.voxel),
            table_w.data.eq(self.table_write.payload.entry),
            table_w.en.eq(self.table_write.valid),
        ]

        # The issue slot. `first`: the table entry on table_r.data belongs to the slot's voxel.
        busy = Signal()                              # a voxel occupies the slot
        first = Signal()
        next_address = Signal(proto.address_width)
        left = Signal(proto.count_width)             # records left after the last issued one
        remaining = Signal(proto.count_width)        # records left, including this cycle's
        address = Signal(proto.address_width)
        m.d.comb += [
            remaining.eq(Mux(first, table_r.data.count, left)),
            address.eq(Mux(first, table_r.data.start, next_address)),
            self.step.eq(busy & self.enable),
            self.issue.eq(busy & self.enable & (remaining != 0)),
            self.free.eq(~busy | (self.enable & (remaining <= 1))),
            self.voxels.ready.eq(self.free),
        ]
        accept = self.voxels.valid & self.voxels.ready
        m.d.comb += [
            table_r.addr.eq(self.voxels.payload),
            table_r.en.eq(accept),                   # hold the entry while the voxel streams
            patch_r.addr.eq(address),
            patch_r.en.eq(self.issue),
        ]
        with m.If(busy & self.enable):
            m.d.sync += [
                first.eq(0),
                next_address.eq(address + 1),
                left.eq(Mux(remaining != 0, remaining - 1, 0)),
            ]
        with m.If(accept):
            m.d.sync += [busy.eq(1), first.eq(1)]
        with m.Elif(self.free):
            m.d.sync += busy.eq(0)

        # memory read (1 cycle), then the broadcast register (1 cycle)
        read_valid = Signal()
        m.d.sync += read_valid.eq(self.issue)
        m.d.sync += [
            self.records.valid.eq(read_valid),
            self.records.payload.eq(patch_r.data),
        ]
        if self._exact_read:        # the address travels beside the record
            read_address = Signal(proto.address_width)
            m.d.sync += [read_address.eq(address), self.record_address.eq(read_address)]
        return m

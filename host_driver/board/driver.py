"""The host side of the board protocol: block rays in, commands out over P transports, blocked
bits and counters back.

:class:`BoardDriver` is a :class:`~blockray.board.Board` towards the render loop. It quantises the
scene and partitions the patch records over the P boards (:mod:`blockray.memory`, as the model
does), identifies every board, loads its memories, turns each batch of block rays into command
records (:mod:`blockray.protocol`), encodes them in the wire format, sends them through each
board's :class:`~blockray.host_driver.board.transport.Transport`, decodes the results and keeps the
counters. Nothing of the model is used for the answer: the blocked bits and every counter come
from the boards.

Counters. The host sends ``IDENTIFY`` and the memory load, then ``READ_COUNTERS``; after each
batch of blocks another ``READ_COUNTERS``. A batch's board cycles on board b are the difference of
the two snapshots minus one (the earlier ``READ_COUNTERS``'s own cycle, docs/board-protocol.md),
its tests the difference; ``load_cycles_per_board`` is the first snapshot minus IDENTIFY's cycle.
From these the driver forms exactly the model's report (:class:`~blockray.board.CountingBoard`).
``link`` in the report counts the bytes on the links.

Rays made on the board (``--traversal board``: :meth:`load` given a
:class:`~blockray.host_driver.traverse.board_walk.LatticeGrid`): the load also sends LOAD_SAMPLES
and LOAD_GRID, and each batch goes as COLUMN and RECEIVERS commands (:mod:`blockray.board_rays`)
instead of its blocks' points and voxels; the board makes the same blocks. One board (P = 1),
built with the block sequencer: its IDENTIFY answers version ``RAYS_VERSION`` (the model's, the
Verilated board's, the ULX3S bitstream's).
"""

import numpy as np

from ...board import BlockBatch, CountingBoard
from ...board_rays import LoadGrid, LoadSamples, RayProtocol, column_commands, record_addresses
from ...cell import Cell, check_cell
from ...errors import CapacityError, ParameterError, option
from ...fixedpoint import DEFAULT_MAX_ERROR
from ...memory import BoardMemories, check_partition
from ...params import BoardParams
from ...protocol import (CELL_FIELDS, MAGIC, RAYS_VERSION, VERSION, BoardProtocol, Identify, ReadCounters, ResultKind,
                        check_capacity, fit_params, identity_cell)
from .framed import integrity_report
from .transport import TransportError

__all__ = ["BoardDriver", "blocked_bits"]


def blocked_bits(words, rows, cols):
    """Blocked words (bit r * cols + s) -> (K, rows, cols) bool."""
    n = (rows * cols + 7) // 8
    if not words:
        return np.zeros((0, rows, cols), dtype=bool)
    raw = np.frombuffer(b"".join(int(w).to_bytes(n, "little") for w in words), dtype=np.uint8)
    bits = np.unpackbits(raw.reshape(len(words), n), axis=1, bitorder="little")[:, :rows * cols]
    return bits.reshape(len(words), rows, cols).astype(bool)


def _decode(protocol, b, transport, data):
    """One result; a corrupted one (an unknown tag) is a TransportError naming the link."""
    try:
        return protocol.decode_result(data)
    except ParameterError as e:
        where = getattr(transport, "where", "the link")
        raise TransportError(f"board {b} ({where}): a corrupted result: {e}") from None


class BoardDriver(CountingBoard):
    """P boards behind the host's Board interface, each reached through its own transport.

    ``transport(params, board)`` opens board ``board``'s :class:`Transport` for the built
    configuration ``params``. ``fit``: size the boards' memories for the scene
    (:func:`~blockray.protocol.fit_params`, simulated boards built per scene); otherwise the
    boards are built for ``params`` as given (real hardware). Either way a scene that does not fit
    ``params``' memories raises :class:`CapacityError` before any transport opens (followed by
    ``hint``, what to change, if given). ``params.bits`` (None by default: chosen for the scene),
    ``max_error``, ``partition``: as :class:`~blockray.sim.model.ModelBoard`; ``cell``: the
    boards' :class:`~blockray.cell.Cell` (their timing; the transports build the boards with it).
    """

    def __init__(self, params=None, *, transport, name="driver", fit=True,
                 max_error=DEFAULT_MAX_ERROR, partition="deal", cell=Cell(), hint=None):
        self._take(params or BoardParams(bits=None))
        self.hint = hint
        self.cell = check_cell(cell)
        self.name = name
        self.max_error, self.fit = max_error, fit
        self.partition = check_partition(partition)
        self._open = transport
        self.transports = []
        self.quantised = None
        self.timing = None
        self.board_params = None
        self.identities = []
        self._stats = {}
        self._reset_counters()

    # -- Board interface -------------------------------------------------------------------------

    def prepare(self, scene, samples):
        # with the filtered cell the drain of a batch's last END_BLOCK depends on the data: the
        # report counts its least (the boards' own cycles are exact)
        self._quantise(scene, samples)
        self._samples = samples

    def load(self, grid):
        if self.quantised is None:
            raise RuntimeError("prepare() before load()")
        p = self.params
        self.memory = mem = BoardMemories(self.quantised, grid, p, self.partition)
        try:
            check_capacity(p, records=mem.records, voxels=mem.nvox)     # before any transport opens
        except CapacityError as e:
            if self.hint is None:
                raise
            raise CapacityError(f"{e.spelled(option)}; {self.hint}") from None
        self.board_params = fit_params(p, records=mem.records, voxels=mem.nvox) if self.fit else p
        self.protocol = BoardProtocol(self.board_params)
        self._read_counters = self.protocol.encode(ReadCounters())
        self.close()
        self._bytes_sent = self._bytes_received = 0
        self.transports = [self._open(self.board_params, b) for b in range(p.boards)]
        self.identities = self.identify()
        self.rays = self._rays_on_board(grid) if getattr(grid, "lattice", False) else None
        setup = b"" if self.rays is None else self.rays.encode_all(
            [LoadSamples(tuple(map(tuple, self._samples.weights.tolist()))), LoadGrid(tuple(grid.origin), grid.shift, grid.v)])
        batches = [self.protocol.encode_all(mem.load_commands(b)) + setup + self._read_counters for b in range(p.boards)]
        snaps = self._exchange(batches, blocks=0)
        self._last = {name: snaps[name] for name in ("cycles", "tests_issued", "tests_useful")}
        self.load_cycles = [int(c) - 1 for c in snaps["cycles"]]          # minus IDENTIFY's own cycle

    def run(self, blocks):
        if not self.transports:
            raise RuntimeError("load() before run()")
        if not blocks:
            return []
        p = self.params
        for block in blocks:
            self.check_block(block)
        batch = BlockBatch.from_blocks(blocks)
        if self.rays is None:
            wire = self._block_wire(batch)
        else:
            wire = self.rays.encode_all(column_commands(batch, self._address, self._samples.count, p.cols))
        snaps, words = self._exchange([wire + self._read_counters] * p.boards, blocks=len(blocks))
        diff = {name: snaps[name] - self._last[name] for name in self._last}
        self._last = snaps
        self._add_batch(diff["cycles"] - 1)                               # (P,)
        self._issued_b += diff["tests_issued"]
        self._useful_b += diff["tests_useful"]
        self._blocks += len(blocks)
        self._rays += sum(b.rays for b in blocks)
        self._voxels += sum(len(b.voxels) for b in blocks)
        self._links_used.update(range(p.boards))
        bits = np.logical_or.reduce(words).reshape(len(blocks), p.rows, p.cols)
        return [bits[k, :len(bl.receiver_patch), :len(bl.shooter_patch)].copy() for k, bl in enumerate(blocks)]

    def _block_wire(self, batch):
        """The command stream of a batch's block rays (each block's :meth:`BoardMemories.block_commands
        <blockray.memory.BoardMemories.block_commands>`), encoded in bulk."""
        q = self.memory.q
        return self.protocol.encode_blocks(q.end_points(batch.receiver_patch, batch.receiver_weights), batch.row_off,
                                           q.shooters[batch.shooter_patch, batch.shooter_sample], batch.col_off,
                                           batch.voxels, batch.vox_off)

    def _rays_on_board(self, grid):
        """The protocol of rays made on the board, once every board can take it; each patch's
        record address."""
        if getattr(self._samples, "drawn", False):
            raise ParameterError(f"{option('traversal')} board loads one sample scheme for every patch, not "
                                 f"points drawn per patch")
        if self.params.boards != 1:
            raise CapacityError(f"{option('traversal')} board needs one board ({option('boards')} 1): a board "
                                f"makes rays from the patch records it holds")
        if not all(ident["version"] == RAYS_VERSION for ident in self.identities):
            raise CapacityError(f"{option('traversal')} board needs a board that makes its rays (built with the "
                                f"block sequencer: IDENTIFY version {RAYS_VERSION}, as {option('backend')} model-link), "
                                f"not {self.name}")
        self._address = record_addresses(self.memory.memories[0]["patch"], len(self.quantised.vertices))
        return RayProtocol(self.board_params)

    def counters(self):
        out = super().counters()
        bp = self.board_params
        rays, links = max(1, self._rays), max(1, len(self._links_used))
        block_bytes = self._block_bytes_sent + self._block_bytes_received
        out["link"] = {
            "bytes_sent": self._bytes_sent, "bytes_received": self._bytes_received,
            "block_bytes_sent": self._block_bytes_sent, "block_bytes_received": self._block_bytes_received,
            "voxels_per_block": self._voxels / max(1, self._blocks),
            "rays_per_block": self._rays / max(1, self._blocks),
            # one board's link (every board gets the same block commands and sends its results)
            "bytes_per_ray": block_bytes / links / rays,
        }
        stats = [t.stats() for t in self.transports] if self.transports else self._stats.get("transports")
        out["driver"] = {
            "backend": self.name,
            "params": None if bp is None else {"rows": bp.rows, "cols": bp.cols, "boards": bp.boards, "bits": bp.bits,
                                               "patch_depth": bp.patch_depth, "voxel_depth": bp.voxel_depth},
            "transports": stats,
        }
        integrity = integrity_report(stats or [])
        if integrity is not None:           # a framed link: frames resent and errors seen
            out["link_integrity"] = integrity
        return out

    def _reset_counters(self):
        super()._reset_counters()
        self._bytes_sent = self._bytes_received = 0
        self._block_bytes_sent = self._block_bytes_received = 0
        self._voxels = 0
        self._links_used = set()

    # -- the links ---------------------------------------------------------------------------------

    def identify(self):
        """Send IDENTIFY to every board; check each answers with the protocol's magic and version
        and the configuration the host expects. Returns the identities (``version``
        :data:`~blockray.protocol.RAYS_VERSION`: the board makes its rays)."""
        want = self.protocol.identity(cell=self.cell)
        out = self.identities_of(self.transports, self.protocol)
        self._bytes_sent += len(self.protocol.encode(Identify())) * len(self.transports)
        self._bytes_received += self.protocol.result_bytes(ResultKind.IDENTITY) * len(self.transports)
        for b, ident in enumerate(out):
            diff = [f"{k} {ident[k]} (host {want[k]})" for k in want
                    if k not in ("version", *CELL_FIELDS) and ident[k] != want[k]]
            if any(ident[k] != want[k] for k in CELL_FIELDS):      # the cell sets the board's cycles
                diff.append(f"cell {identity_cell(ident)} (host {identity_cell(want)}; {option('cell')})")
            if diff:
                raise CapacityError(f"board {b} was built for another configuration: {', '.join(diff)}")
        return out

    @staticmethod
    def identities_of(transports, protocol):
        """What each board behind ``transports`` answers to IDENTIFY (an IDENTIFY and its result
        do not depend on the configuration: any ``protocol`` reads them), each checked to be a
        blockray board of this protocol's magic and version."""
        n = protocol.result_bytes(ResultKind.IDENTITY)
        request = protocol.encode(Identify())
        for t in transports:
            t.send(request)
            t.expect(n)
        out = []
        for b, t in enumerate(transports):
            got = _decode(protocol, b, t, t.recv(n))
            if got.kind is not ResultKind.IDENTITY:
                raise TransportError(f"board {b}: answered IDENTIFY with a {got.kind.name} result")
            ident = got.identity
            if ident["magic"] != MAGIC or ident["version"] not in (VERSION, RAYS_VERSION):
                raise TransportError(f"board {b}: magic {ident['magic']:#06x} version {ident['version']} is not a "
                                     f"blockray board of protocol version {VERSION} or {RAYS_VERSION} (magic "
                                     f"{MAGIC:#06x})")
            try:
                identity_cell(ident)
            except ParameterError as e:
                raise TransportError(f"board {b}: {e}") from None
            out.append(ident)
        return out

    def _decode(self, b, transport, data):
        return _decode(self.protocol, b, transport, data)

    def _recv(self, transport, n):
        data = transport.recv(n)
        self._bytes_received += len(data)
        return data

    def _exchange(self, batches, *, blocks):
        """Send each board its batch (``blocks`` END_BLOCKs then one READ_COUNTERS); return the
        counter snapshots as (P,) arrays per counter, and (if ``blocks``) each board's blocked bits ((blocks, R * S) bool)."""
        proto = self.protocol
        nb, nc = proto.result_bytes(ResultKind.BLOCKED), proto.result_bytes(ResultKind.COUNTERS)
        expect = blocks * nb + nc
        for t, data in zip(self.transports, batches):
            t.send(data)
            t.expect(expect)
            self._bytes_sent += len(data)
        if blocks:
            self._block_bytes_sent += sum(len(d) for d in batches)
            self._block_bytes_received += expect * len(batches)
        snaps = {name: [] for name in ("cycles", "tests_issued", "tests_useful")}
        words = []
        for b, t in enumerate(self.transports):
            data = self._recv(t, expect)
            tags, bits = proto.decode_blocked(data, blocks)
            if (tags != ResultKind.BLOCKED).any():      # decoded one by one: the error names what came
                results = [self._decode(b, t, data[k * nb:(k + 1) * nb]) for k in range(blocks)]
                raise TransportError(f"board {b}: result kinds {[r.kind.name for r in results[:8]]}... do not "
                                     f"follow the commands")
            last = self._decode(b, t, data[blocks * nb:])
            if last.kind is not ResultKind.COUNTERS:
                raise TransportError(f"board {b}: answered READ_COUNTERS with a {last.kind.name} result")
            words.append(bits)
            for name in snaps:
                snaps[name].append(last.counters[name])
        snaps = {name: np.array(v, dtype=np.int64) for name, v in snaps.items()}
        return (snaps, words) if blocks else snaps

    def close(self):
        """Close the transports (``render`` calls this at the end)."""
        if self.transports:
            self._stats = {"transports": [t.stats() for t in self.transports]}
        for t in self.transports:
            t.close()
        self.transports = []


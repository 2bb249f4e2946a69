"""The board's host protocol: command and result record layouts, packing, capacity checks.

One definition serves the gateware (stream payloads), the bit-exact model, cocotb and the host:
records are :mod:`amaranth.lib.data` layouts built from :class:`~blockray.params.BoardParams`,
packed and unpacked only with :func:`blockray.records.pack` / :func:`~blockray.records.unpack`.
See docs/board-protocol.md for the semantics of each command, the cycle contract and reset.

A **command** is ``{op, arg}``: ``op`` a :class:`blockray.timing.Op` (3 bits), ``arg`` a union
with one member per command that has operands. A **result** is ``{kind, data}``: ``kind`` a
:class:`ResultKind`, ``data`` a union of the R x S ``blocked`` word (bit ``r * S + s``) and the
``counters`` snapshot.

Address widths come from the memory sizes ("model only what a scene needs"): a patch address is
``ceil(log2(patch_depth))`` bits, a record count ``bits_for(patch_depth)`` (a voxel may hold the
whole memory), a voxel number ``ceil(log2(voxel_depth))`` bits. :func:`fit_params` gives the
smallest memories for a scene's partition and :func:`check_capacity` raises
:class:`~blockray.errors.CapacityError` before anything is simulated.
"""

import enum
from dataclasses import dataclass

from amaranth.hdl import Shape, unsigned
from amaranth.lib import data
from amaranth.utils import bits_for, ceil_log2

from ..errors import CapacityError, ParameterError
from ..params import BoardParams
from ..records import pack, patch_layout, point_layout, unpack
from ..timing import POINTS_PER_LOAD, Op

__all__ = ["ResultKind", "COUNTERS", "COUNTER_WIDTH", "BoardProtocol", "BoardResult",
           "fit_params", "check_capacity", "RESULT_OPS", "result_producers", "replay_after_reset",
           "ReplayingHost", "describe"]

#: the counters of a READ_COUNTERS result, in layout order (docs/board-protocol.md defines them)
COUNTERS = ("cycles", "busy", "tests_issued", "tests_useful", "stalls")
#: bits per counter: 2**48 cycles is 32 days at 100 MHz
COUNTER_WIDTH = 48


class ResultKind(enum.IntEnum):
    """What a result record holds."""
    BLOCKED = 0     # END_BLOCK: the R x S blocked bits
    COUNTERS = 1    # READ_COUNTERS: the counter snapshot


@dataclass(frozen=True)
class BoardResult:
    """A decoded result record: ``blocked`` (int, bit r*S + s) or ``counters`` (dict)."""
    kind: ResultKind
    blocked: int = None
    counters: dict = None


def _index_width(n):
    return max(1, ceil_log2(n))


class BoardProtocol:
    """Record layouts and packing for one board configuration (``params``)."""

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
        self.result_layout = data.StructLayout({
            "kind": ResultKind,
            "data": data.UnionLayout({
                "blocked": unsigned(params.processors),
                "counters": self.counters_layout,
            }),
        })

    @property
    def params(self):
        return self._params

    # -- host side -------------------------------------------------------------------------------

    def command_value(self, command):
        """The layout value (nested dict) of a command ``(op, index, value)``.

        ``command`` is anything with ``op``, ``index`` and ``value`` attributes, such as
        :class:`blockray.sim.model.Command`: WRITE_PATCH index = address, value = packed patch
        record; WRITE_VOXEL index = voxel, value = (start, count); LOAD_RECEIVER / LOAD_SHOOTER
        index = row / column, value = (x, y, z); LOAD_POINTS value = up to
        :data:`~blockray.timing.POINTS_PER_LOAD` ``(shooter, index, (x, y, z))`` with ``shooter``
        False for a receiver row, True for a shooter column; VOXEL index = voxel.
        """
        p = self._params
        op = Op(command.op)
        index = int(command.index)
        if op is Op.WRITE_PATCH:
            self._check(index, p.patch_depth, "patch address", "patch_depth")
            arg = {"write_patch": {"address": index,
                                   "patch": unpack(patch_layout(p.bits), command.value)}}
        elif op is Op.WRITE_VOXEL:
            self._check(index, p.voxel_depth, "voxel", "voxel_depth")
            start, count = (int(x) for x in command.value)
            if start < 0 or count < 0 or start + count > p.patch_depth:
                raise CapacityError(f"voxel {index}: records {start}..{start + count - 1} are outside "
                                    f"patch memory (patch_depth {p.patch_depth})")
            if count == 0:
                start = 0       # an empty voxel's start is never read; keep it in range
            arg = {"write_voxel": {"voxel": index, "entry": {"start": start, "count": count}}}
        elif op in (Op.LOAD_RECEIVER, Op.LOAD_SHOOTER):
            receiver = op is Op.LOAD_RECEIVER
            self._check(index, p.rows if receiver else p.cols,
                        "receiver row" if receiver else "shooter column", "rows" if receiver else "cols")
            point = dict(zip("xyz", (int(c) for c in command.value)))
            if receiver:
                arg = {"load_receiver": {"row": index, "point": point}}
            else:
                arg = {"load_shooter": {"col": index, "point": point}}
        elif op is Op.LOAD_POINTS:
            slots = list(command.value)
            if not 1 <= len(slots) <= POINTS_PER_LOAD:
                raise ParameterError(f"LOAD_POINTS carries 1 to {POINTS_PER_LOAD} points, not {len(slots)}")
            arg = {"load_points": []}
            for shooter, where, point in slots:
                self._check(int(where), p.cols if shooter else p.rows,
                            "shooter column" if shooter else "receiver row", "cols" if shooter else "rows")
                arg["load_points"].append({"valid": 1, "shooter": int(bool(shooter)), "index": int(where),
                                           "point": dict(zip("xyz", (int(c) for c in point)))})
            empty = {"valid": 0, "shooter": 0, "index": 0, "point": {"x": 0, "y": 0, "z": 0}}
            arg["load_points"] += [empty] * (POINTS_PER_LOAD - len(slots))
        elif op is Op.VOXEL:
            self._check(index, p.voxel_depth, "voxel", "voxel_depth")
            arg = {"voxel": {"voxel": index}}
        else:
            arg = {}
        return {"op": op, "arg": arg}

    def encode(self, command):
        """Pack one command into its record (an int of ``command_layout.size`` bits)."""
        return pack(self.command_layout, self.command_value(command))

    def encode_all(self, commands):
        return [self.encode(c) for c in commands]

    def decode_command(self, word):
        """Unpack a command record: ``{"op": Op, "arg": {member: ...}}`` (every union member)."""
        value = unpack(self.command_layout, word)
        value["op"] = Op(value["op"])
        return value

    def encode_result(self, result):
        """Pack a :class:`BoardResult` (used by models and tests)."""
        if result.kind is ResultKind.BLOCKED:
            return pack(self.result_layout, {"kind": result.kind, "data": {"blocked": result.blocked}})
        return pack(self.result_layout, {"kind": result.kind, "data": {"counters": result.counters}})

    def decode_result(self, word):
        """Unpack a result record into a :class:`BoardResult`."""
        value = unpack(self.result_layout, word)
        kind = ResultKind(value["kind"])
        if kind is ResultKind.BLOCKED:
            return BoardResult(kind, blocked=value["data"]["blocked"])
        return BoardResult(kind, counters=value["data"]["counters"])

    @staticmethod
    def _check(index, depth, what, param):
        if not 0 <= index < depth:
            raise CapacityError(f"{what} {index} does not fit the board ({param} {depth})")


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


# -- host side: ordering and replay after a reset ---------------------------------------------------

#: commands that put a result record on the result stream (one each, in command order)
RESULT_OPS = (Op.END_BLOCK, Op.READ_COUNTERS)
#: commands whose effect (board memory) outlives a block
MEMORY_OPS = (Op.WRITE_PATCH, Op.WRITE_VOXEL)


def result_producers(commands):
    """Indices of the commands that produce a result, in the order their results arrive."""
    return [i for i, c in enumerate(commands) if Op(c.op) in RESULT_OPS]


def replay_after_reset(commands, answered):
    """What the host sends after a board reset, given that the results of the first ``answered``
    result-producing commands of ``commands`` have been received.

    A reset loses board memory, the block in progress, every queued command and every result not
    yet received. The host replays from the start of the block holding the first unanswered
    result (or from just after the last answered one), preceded by every memory write before that
    point. Returns a list of ``(original index, command)``; results of replayed commands that were
    already answered (a READ_COUNTERS inside the replayed block) must be dropped by the host, so
    it receives every result exactly once and in order (:class:`ReplayingHost` does this).
    """
    producers = result_producers(commands)
    if not 0 <= answered <= len(producers):
        raise ValueError(f"{answered} results answered, but the stream has {len(producers)}")
    restart = producers[answered] if answered < len(producers) else (
        producers[-1] + 1 if producers else 0)
    # back to the BEGIN_BLOCK of the block that is open at `restart`, if any
    for i in range(min(restart, len(commands)) - 1, -1, -1):
        op = Op(commands[i].op)
        if op is Op.END_BLOCK:
            break
        if op is Op.BEGIN_BLOCK:
            restart = i
            break
    replay = [(i, c) for i, c in enumerate(commands[:restart]) if Op(c.op) in MEMORY_OPS]
    replay += [(i, c) for i, c in enumerate(commands) if i >= restart]
    return replay


class ReplayingHost:
    """Host bookkeeping for one board's batch across resets: which commands to send next and which
    received results to keep.

    ``pending()`` gives the ``(original index, command)`` list to send (the whole batch at first,
    a replay after :meth:`reset`); :meth:`receive` takes result words in arrival order and keeps each
    original result exactly once. ``results`` maps original command index -> result word.
    """

    def __init__(self, commands):
        self.commands = list(commands)
        self.producers = result_producers(self.commands)
        self.results = {}
        self.resets = 0
        self._stream = list(enumerate(self.commands))
        self._expect = [i for i, c in self._stream if Op(c.op) in RESULT_OPS]

    def pending(self):
        return list(self._stream)

    def receive(self, word):
        """A result word arrived. Returns the original command index it answers (or None if it
        duplicates one already kept)."""
        if not self._expect:
            raise AssertionError("a result arrived that no command asked for")
        index = self._expect.pop(0)
        if index in self.results:
            return None
        self.results[index] = word
        return index

    @property
    def answered(self):
        n = 0
        while n < len(self.producers) and self.producers[n] in self.results:
            n += 1
        return n

    @property
    def done(self):
        return len(self.results) == len(self.producers)

    def reset(self):
        """The board was reset: plan the replay."""
        self.resets += 1
        self._stream = replay_after_reset(self.commands, self.answered)
        self._expect = [i for i, c in self._stream if Op(c.op) in RESULT_OPS]


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
    """Markdown tables of the command and result records for ``params`` (docs/board-protocol.md
    embeds the output for the default parameters; a test keeps them equal)."""
    proto = BoardProtocol(params)
    out = [f"Parameters: `{params!r}`", "",
           f"Command record: {proto.command_layout.size} bits. `op` (bits "
           f"{Shape.cast(Op).width - 1}:0) selects the member of `arg`.", ""]
    arg_offset = proto.command_layout["arg"].offset
    out.append("| op | value | `arg` member |")
    out.append("|---|---|---|")
    members = {Op.WRITE_PATCH: "write_patch", Op.WRITE_VOXEL: "write_voxel", Op.LOAD_RECEIVER: "load_receiver",
               Op.LOAD_SHOOTER: "load_shooter", Op.VOXEL: "voxel", Op.LOAD_POINTS: "load_points"}
    for op in Op:
        out.append(f"| {op.name} | {op.value} | {('`' + members[op] + '`') if op in members else '(none)'} |")
    for op, name in members.items():
        out += ["", f"`arg.{name}` ({op.name}):", "",
                _table(proto.arg_layout[name].shape, f"arg.{name}", arg_offset)]
    res_offset = proto.result_layout["data"].offset
    out += ["", f"Result record: {proto.result_layout.size} bits. `kind` (bit 0): "
            + ", ".join(f"{k.value} = {k.name}" for k in ResultKind) + ".", "",
            "`data.blocked` (END_BLOCK): bit `r * S + s` of the field is ray (shooter column s, receiver row r).", "",
            _table(proto.result_layout["data"].shape["blocked"].shape, "data.blocked", res_offset), "",
            "`data.counters` (READ_COUNTERS):", "",
            _table(proto.counters_layout, "data.counters", res_offset)]
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    print(describe(BoardParams()))

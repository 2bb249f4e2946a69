"""Host-side checking shared by the Amaranth-simulator and cocotb board tests.

:class:`BatchRun` is the testbench's host for one board's batch, simulator-neutral and built on
the one drive loop (:class:`blockray.sim.drive.StreamHost`: random idle and back-pressure with
bursts) and :class:`ReplayingHost` (reset mid-batch, replay; the host driver never resets a
board mid-render, so the replay plan lives here, with the test of the board's reset). It drives either
:class:`~blockray.rtl.core.BoardCore` (``link="bytes"``: commands in the wire format, results
split from the byte stream) or :class:`~blockray.rtl.board.BoardTop` (``link="records"``: one
command record per transfer). It records a :class:`RunLog` (the cocotb bench's monitor and
driver); :func:`check_run` is the scoreboard: it compares the log with the bit-exact model
(:class:`blockray.sim.model.BoardModel`, the reference model) with zero tolerance.
"""

from dataclasses import dataclass, field

from blockray.protocol import BoardProtocol, Op, ResultKind
from blockray.sim.drive import HostTiming, StreamHost
from blockray.sim.model import BoardModel

__all__ = ["RunLog", "BatchRun", "expected_results", "check_run", "ReplayingHost", "replay_after_reset"]

MODEL_COUNTERS = ("cycles", "busy", "tests_issued", "tests_useful")


# ---------------------------------------------------------------------------- replay after a reset

#: commands that put a result record on the result stream (one each, in command order)
RESULT_OPS = (Op.END_BLOCK, Op.READ_COUNTERS, Op.IDENTIFY)
#: commands whose effect (board memory) outlives a block
MEMORY_OPS = (Op.WRITE_PATCH, Op.WRITE_VOXEL)


def result_producers(commands):
    """Indices of the commands that produce a result, in the order their results arrive."""
    return [i for i, c in enumerate(commands) if c.op in RESULT_OPS]


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
        op = commands[i].op
        if op is Op.END_BLOCK:
            break
        if op is Op.BEGIN_BLOCK:
            restart = i
            break
    replay = [(i, c) for i, c in enumerate(commands[:restart]) if c.op in MEMORY_OPS]
    replay += [(i, c) for i, c in enumerate(commands) if i >= restart]
    return replay


class ReplayingHost:
    """Host bookkeeping for one board's batch across resets: which commands to send next and which
    received results to keep.

    ``pending()`` gives the ``(original index, command)`` list to send (the whole batch at first,
    a replay after :meth:`reset`); :meth:`receive` takes results in arrival order and keeps each
    original result exactly once. ``results`` maps original command index -> result.
    """

    def __init__(self, commands):
        self.commands = list(commands)
        self.producers = result_producers(self.commands)
        self.results = {}
        self.resets = 0
        self._stream = list(enumerate(self.commands))
        self._expect = [i for i, c in self._stream if c.op in RESULT_OPS]

    def pending(self):
        return list(self._stream)

    def receive(self, word):
        """A result arrived. Returns the original command index it answers (or None if it
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
        self._expect = [i for i, c in self._stream if c.op in RESULT_OPS]


@dataclass
class RunLog:
    """What the host saw. Cycle numbers count clock edges since the last reset's release."""
    results: dict = field(default_factory=dict)     # original index -> result (record int or wire bytes)
    epoch: dict = field(default_factory=dict)       # original index -> number of resets before it arrived
    accepted: dict = field(default_factory=dict)    # original index -> cycle its command (last byte) was accepted
    received: dict = field(default_factory=dict)    # original index -> cycle its result (last byte) arrived
    answered_at_reset: list = field(default_factory=list)   # host.answered at each reset
    order: list = field(default_factory=list)       # original indices in the order kept

    def receive(self, host, word, cycle):
        """A result arrived in ``cycle``: hand it to the host; log it if the host keeps it."""
        index = host.receive(word)
        if index is not None:
            self.results[index] = word
            self.received[index] = cycle
            self.epoch[index] = host.resets
            self.order.append(index)


class BatchRun:
    """One board's batch ``commands`` under random host timing, with an optional reset after
    ``reset_at`` cycles (see the module docstring). The simulator glue, per cycle: if
    :meth:`reset_due`, reset the board for one edge and call :meth:`after_reset`; else drive
    ``self.stream`` for one edge (:func:`blockray.sim.drive.amaranth_cycle` or the cocotb
    equivalent) and call :meth:`after_cycle` with the item received."""

    def __init__(self, params, commands, *, link="bytes", idle=HostTiming(), backpressure=HostTiming(),
                 seed=0, reset_at=None, max_cycles=10_000_000, encode=None):
        self.proto = BoardProtocol(params)
        self.link, self.reset_at, self.max_cycles = link, reset_at, max_cycles
        self._encode = encode or self.proto.encode         # a test may send other bytes
        self.host = ReplayingHost(commands)
        self.stream = StreamHost(idle=idle, backpressure=backpressure, seed=seed)
        self.log = RunLog()
        self.total = 0              # clock edges, resets included
        self._send(self.host.pending())

    def _send(self, pending):
        items, ends = [], []
        for index, command in pending:
            if self.link == "bytes":
                items += self._encode(command)
            else:
                items.append(self.proto.record(command))
            ends.append((len(items), index))
        self._ends = ends[::-1]                         # (items taken when accepted, index), popped
        self._reader = self.proto.reader()
        self.stream.send(items)

    @property
    def done(self):
        return self.host.done

    def reset_due(self):
        self.total += 1
        if self.total > self.max_cycles:
            raise AssertionError("the board stopped making progress")
        return self.reset_at is not None and self.total == self.reset_at

    def after_reset(self):
        self.log.answered_at_reset.append(self.host.answered)
        self.host.reset()
        self.stream.reset()
        self._send(self.host.pending())

    def after_cycle(self, item):
        cycle = self.stream.cycles - 1
        while self._ends and self._ends[-1][0] <= self.stream.taken:
            self.log.accepted[self._ends.pop()[1]] = cycle
        if item is None:
            return
        words = self._reader.feed(bytes([item])) if self.link == "bytes" else [item]
        for word in words:
            self.log.receive(self.host, word, cycle)


def expected_results(params, commands, timing=None, *, model=BoardModel):
    """{original index: ("blocked", word) | ("counters", dict) | ("identity", dict)} from the model
    (``model(params, timing)``: a :class:`BoardModel` by default)."""
    res = model(params, timing).execute([c for _, c in commands])
    results = iter(res.results)
    out = {}
    for i, c in commands:
        if c.op in RESULT_OPS:
            r = next(results)
            out[i] = {ResultKind.BLOCKED: ("blocked", r.blocked), ResultKind.COUNTERS: ("counters", r.counters),
                      ResultKind.IDENTITY: ("identity", r.identity)}[r.kind]
    return out, res


def check_run(params, commands, log, *, model=BoardModel):
    """Assert the run's results equal the model's: blocked words against the uninterrupted batch,
    counters against the model run on the stream the board actually executed since its last
    reset, every result exactly once and in order, and cycles + stalls within the window the host
    saw."""
    proto = BoardProtocol(params)
    producers = [i for i, c in enumerate(commands) if c.op in RESULT_OPS]
    assert sorted(log.results) == producers, "results lost or duplicated"
    assert log.order == producers, "results reordered"

    # the stream executed in each epoch (after reset k: the replay planned at that reset)
    streams = [list(enumerate(commands))]
    for answered in log.answered_at_reset:
        streams.append(replay_after_reset(commands, answered))
    expect = [expected_results(params, s, model=model)[0] for s in streams]

    full = expect[0]
    for i in producers:
        raw = log.results[i]
        got = proto.decode_result(raw)
        kind, want = expect[log.epoch[i]][i]
        if isinstance(raw, bytes):
            assert len(raw) == proto.result_bytes(got.kind), f"command {i}: {len(raw)} result bytes"
        if kind == "blocked":
            assert got.kind is ResultKind.BLOCKED, f"command {i}: expected a blocked word, got {got}"
            assert got.blocked == want == full[i][1], (
                f"command {i}: blocked word {got.blocked:#x}, model {want:#x}")
        elif kind == "identity":
            assert got.kind is ResultKind.IDENTITY and got.identity == want, f"command {i}: {got}, model {want}"
        else:
            assert got.kind is ResultKind.COUNTERS, f"command {i}: expected counters, got {got}"
            assert {k: got.counters[k] for k in MODEL_COUNTERS} == want, (
                f"command {i} (after {log.epoch[i]} resets): board {got.counters}, model {want}")
            total = got.counters["cycles"] + got.counters["stalls"]
            # the snapshot covers every clock cycle before READ_COUNTERS' own cycle, which is
            # after its acceptance and before its result is seen
            assert log.accepted[i] + 1 <= total <= log.received[i] - 1, (
                f"command {i}: cycles + stalls = {total} outside "
                f"[{log.accepted[i] + 1}, {log.received[i] - 1}]")
    return expect



"""Host-side checking shared by the Amaranth-simulator and cocotb board tests.

A run sends a batch of commands through :class:`blockray.rtl.protocol.ReplayingHost` (with
resets, replays) and records, per result-producing command, the result word, whether it arrived
after a reset, and the cycles (since the last reset) at which its command was accepted and its
result received. :func:`check_run` compares everything with the bit-exact model
(:class:`blockray.sim.model.BoardModel`) with zero tolerance.
"""

from dataclasses import dataclass, field

from blockray.rtl.protocol import BoardProtocol, ResultKind, RESULT_OPS, replay_after_reset
from blockray.sim.model import BoardModel
from blockray.timing import Op

__all__ = ["RunLog", "expected_results", "check_run"]

MODEL_COUNTERS = ("cycles", "busy", "tests_issued", "tests_useful")


@dataclass
class RunLog:
    """What the host saw. Cycle numbers count clock edges since the last reset's release."""
    results: dict = field(default_factory=dict)     # original index -> result word
    epoch: dict = field(default_factory=dict)       # original index -> number of resets before it arrived
    accepted: dict = field(default_factory=dict)    # original index -> cycle its command was accepted
    received: dict = field(default_factory=dict)    # original index -> cycle its result arrived
    answered_at_reset: list = field(default_factory=list)   # host.answered at each reset
    order: list = field(default_factory=list)       # original indices in the order kept

    def receive(self, host, word, cycle):
        """A result word arrived in ``cycle``: hand it to the host; log it if the host keeps it."""
        index = host.receive(word)
        if index is not None:
            self.results[index] = word
            self.received[index] = cycle
            self.epoch[index] = host.resets
            self.order.append(index)


def expected_results(params, commands, timing=None):
    """{original index: ("blocked", word) | ("counters", dict)} from the model."""
    res = BoardModel(params, timing).execute([c for _, c in commands])
    words, counters = iter(res.words), iter(res.counters)
    out = {}
    for i, c in commands:
        if Op(c.op) is Op.END_BLOCK:
            out[i] = ("blocked", next(words))
        elif Op(c.op) is Op.READ_COUNTERS:
            out[i] = ("counters", next(counters))
    return out, res


def check_run(params, commands, log):
    """Assert the run's results equal the model's: blocked words against the uninterrupted batch,
    counters against the model run on the stream the board actually executed since its last
    reset, every result exactly once and in order, and cycles + stalls within the window the host
    saw."""
    proto = BoardProtocol(params)
    producers = [i for i, c in enumerate(commands) if Op(c.op) in RESULT_OPS]
    assert sorted(log.results) == producers, "results lost or duplicated"
    assert log.order == producers, "results reordered"

    # the stream executed in each epoch (after reset k: the replay planned at that reset)
    streams = [list(enumerate(commands))]
    for answered in log.answered_at_reset:
        streams.append(replay_after_reset(commands, answered))
    expect = [expected_results(params, s)[0] for s in streams]

    full = expect[0]
    for i in producers:
        got = proto.decode_result(log.results[i])
        kind, want = expect[log.epoch[i]][i]
        if kind == "blocked":
            assert got.kind is ResultKind.BLOCKED, f"command {i}: expected a blocked word, got {got}"
            assert got.blocked == want == full[i][1], (
                f"command {i}: blocked word {got.blocked:#x}, model {want:#x}")
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


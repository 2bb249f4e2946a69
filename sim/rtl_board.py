"""Render through the simulated RTL board: ``--board amaranth`` and ``--board verilator``.

The Glasgow pattern: :class:`RTLBoard` is the host side of the board protocol
(docs/board-protocol.md) and knows nothing of what answers it. It reuses
:class:`~blockray.sim.model.ModelBoard` for everything the host does (quantisation, partition of
the patches over the P boards, memory images, the command stream of a block ray), packs the
commands with :class:`~blockray.rtl.protocol.BoardProtocol`, hands each board's batch to a
**transport** and decodes the result words the RTL sends back. Nothing of the model's answer is
used: the blocked bits and every counter come from the RTL.

Transports (``execute(batches) -> results``: one list of command words per board in, one list of
result words per board out; the boards run concurrently where the simulator allows):

* :class:`VerilatorTransport`: the P boards' generated Verilog under Verilator, one simulator
  process per board (sim/rtl_harness.py), started once and kept for the whole render, all running
  each batch at once; cocotb (sim/rtl_cocotb.py) is the control plane only: commands go in through
  a ``$readmemh`` file and results come back through a ``$fwrite`` log, so the simulation runs free
  between host calls (no Python per cycle).
* :class:`AmaranthTransport`: the P boards in the Amaranth simulator, driven by a Python
  testbench every cycle (small scenes, debugging, waveforms).

Counters. After the memory load and after every block the host sends ``READ_COUNTERS``; a block's
board cycles on board b are the difference of the two snapshots minus one (the earlier
``READ_COUNTERS``'s own cycle, docs/board-protocol.md), its tests the difference. The host then
forms exactly the model's report: ``board_cycles`` = per batch the slowest board plus the last
END_BLOCK's drain, summed;
``board_cycles_per_board``, ``tests_issued``, ``tests_useful``, ``utilization`` as
:meth:`ModelBoard.counters`; ``load_cycles_per_board`` from the snapshot after the load.
"""

import json
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import weakref
from pathlib import Path

import numpy as np

from ..errors import BlockrayError, ParameterError
from ..records import leaves
from ..rtl.protocol import BoardProtocol, ResultKind, RESULT_OPS, check_capacity, fit_params
from ..timing import Op
from .model import Command, ModelBoard, partition_records, registration

__all__ = ["Transport", "VerilatorTransport", "AmaranthTransport", "ResultDecoder", "RTLBoard", "BACKENDS"]

BACKENDS = ("amaranth", "verilator")
HERE = Path(__file__).resolve().parent


class SimulationError(BlockrayError):
    """The simulated board did not answer as the protocol says."""


# -- result words -------------------------------------------------------------------------------

class ResultDecoder:
    """Vectorised :meth:`BoardProtocol.decode_result` for many words: field offsets read from
    the protocol's ``result_layout`` (blockray.records.leaves), so it cannot drift from it."""

    def __init__(self, protocol):
        self.protocol = protocol
        fields = {path: (offset, shape.width) for path, offset, shape in leaves(protocol.result_layout)}
        self.kind = fields[("kind",)]
        self.blocked = fields[("data", "blocked")]
        self.counters = {path[-1]: fields[path] for path in fields if path[:2] == ("data", "counters")}

    @staticmethod
    def _field(words, field):
        offset, width = field
        mask = (1 << width) - 1
        return [(w >> offset) & mask for w in words]

    def kinds(self, words):
        return self._field(words, self.kind)

    def blocked_words(self, words):
        return self._field(words, self.blocked)

    def counter_array(self, words, name):
        return np.array(self._field(words, self.counters[name]), dtype=np.int64)


def blocked_bits(words, rows, cols):
    """Blocked words (bit r * cols + s) -> (K, rows, cols) bool."""
    n = (rows * cols + 7) // 8
    if not words:
        return np.zeros((0, rows, cols), dtype=bool)
    raw = np.frombuffer(b"".join(int(w).to_bytes(n, "little") for w in words), dtype=np.uint8)
    bits = np.unpackbits(raw.reshape(len(words), n), axis=1, bitorder="little")[:, :rows * cols]
    return bits.reshape(len(words), rows, cols).astype(bool)


# -- transports ---------------------------------------------------------------------------------

class Transport:
    """Moves command words to P boards and their result words back. ``execute(batches)``: one
    sequence of command words per board (the same object may serve several boards); returns one
    list of result words per board, in order. ``cycles``: clock cycles simulated so far."""

    boards = 0
    cycles = 0
    #: wall seconds the host waited for the simulator (Verilator: the simulation's own run time)
    simulator_seconds = 0.0

    def execute(self, batches):
        raise NotImplementedError

    def execute_one(self, board, words):
        """Run ``words`` on board ``board`` alone."""
        batches = [[] for _ in range(self.boards)]
        batches[board] = words
        return self.execute(batches)[board]

    def close(self):
        pass


class AmaranthTransport(Transport):
    """P :class:`~blockray.rtl.board.BoardTop` in one Amaranth simulation, kept for the whole
    render. A testbench offers each board its next command every cycle and always takes results
    (no host idles, no back-pressure). ``vcd``: write a waveform of everything simulated."""

    def __init__(self, params, boards, *, vcd=None):
        from amaranth.hdl import Module
        from amaranth.sim import Simulator
        from ..rtl.board import BoardTop

        self.params, self.boards = params, boards
        self.protocol = BoardProtocol(params)
        self._tops = [BoardTop(params) for _ in range(boards)]
        m = Module()
        for b, top in enumerate(self._tops):
            m.submodules[f"board{b}"] = top
        self._sim = Simulator(m)
        self._sim.add_clock(1e-8)
        self._sim.add_testbench(self._testbench)
        self._job = None
        self._vcd = None
        if vcd is not None:
            self._vcd = self._sim.write_vcd(str(vcd))
            self._vcd.__enter__()
        self.cycles = 0

    async def _testbench(self, ctx):
        tops = self._tops
        payloads = [t.commands.payload.as_value() for t in tops]
        results = [t.results.payload.as_value() for t in tops]
        for t in tops:
            ctx.set(t.results.ready, 1)
        while True:
            job = self._job
            if job is None or job["done"]:
                await ctx.tick()
                self.cycles += 1
                continue
            batches, out, ptr = job["batches"], job["out"], job["ptr"]
            offered = [False] * len(tops)
            for b, t in enumerate(tops):
                if ptr[b] < len(batches[b]):
                    ctx.set(payloads[b], batches[b][ptr[b]])
                    ctx.set(t.commands.valid, 1)
                    offered[b] = True
                else:
                    ctx.set(t.commands.valid, 0)
            taken = [offered[b] and ctx.get(t.commands.ready) for b, t in enumerate(tops)]
            words = [ctx.get(results[b]) if ctx.get(t.results.valid) else None for b, t in enumerate(tops)]
            await ctx.tick()
            self.cycles += 1
            for b in range(len(tops)):
                ptr[b] += int(bool(taken[b]))
                if words[b] is not None:
                    out[b].append(words[b])
            if all(ptr[b] == len(batches[b]) and len(out[b]) == job["expects"][b] for b in range(len(tops))):
                for t in tops:
                    ctx.set(t.commands.valid, 0)
                job["done"] = True

    def execute(self, batches):
        if len(batches) != self.boards:
            raise ValueError(f"{len(batches)} batches for {self.boards} boards")
        op = _op_reader(self.protocol)
        self._job = {"batches": [list(w) for w in batches], "out": [[] for _ in batches],
                     "ptr": [0] * len(batches), "expects": [_results_owed(w, op) for w in batches],
                     "done": False}
        while not self._job["done"]:
            self._sim.advance()
        return self._job["out"]

    def close(self):
        if self._vcd is not None:
            self._vcd.__exit__(None, None, None)
            self._vcd = None


def _op_reader(protocol):
    (offset, width), = [(o, s.width) for path, o, s in leaves(protocol.command_layout) if path == ("op",)]
    return offset, (1 << width) - 1


def _results_owed(words, op):
    offset, mask = op
    ops = {int(o) for o in RESULT_OPS}
    return sum(1 for w in words if (w >> offset) & mask in ops)


def _kill(proc, sock):
    try:
        sock.close()
    except OSError:
        pass
    if proc.poll() is None:
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()


class _HarnessProcess:
    """One Verilator simulation of the harness (``boards`` boards) under cocotb, started once and
    kept running; :meth:`submit` starts a batch, :meth:`collect` waits for its results."""

    def __init__(self, build, op, workdir, *, vcd=None, log=None, startup_timeout=600):
        self.build, self._op = build, op
        self.boards = build.boards
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self._commands = self.workdir / "commands.hex"
        self._results = self.workdir / "results.txt"
        self._commands.write_text("0\n")
        self.log_path = Path(log) if log else self.workdir / "simulator.log"
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        listener.settimeout(1.0)
        config = {
            "build_dir": str(build.build_dir), "toplevel": build.toplevel,
            "test_dir": str(self.workdir), "module_dir": str(HERE),
            "port": listener.getsockname()[1],
            "plusargs": [f"+blockray_commands={self._commands}", f"+blockray_results={self._results}"],
            "vcd": str(Path(vcd).resolve()) if vcd is not None else None,
        }
        self._logfile = open(self.log_path, "w")
        self._proc = subprocess.Popen([sys.executable, "-c", "from blockray.sim.rtl_board import _serve; _serve()",
                                       json.dumps(config)], stdout=self._logfile, stderr=subprocess.STDOUT,
                                      cwd=self.workdir)
        t0 = time.perf_counter()
        self._sock = None
        while self._sock is None:
            try:
                self._sock, _ = listener.accept()
            except socket.timeout:
                if self._proc.poll() is not None or time.perf_counter() - t0 > startup_timeout:
                    listener.close()
                    raise SimulationError(f"the Verilator simulation did not start; see {self.log_path}")
        listener.close()
        self._sock.settimeout(None)
        self._stream = self._sock.makefile("rwb")
        self._finalizer = weakref.finalize(self, _kill, self._proc, self._sock)
        self._clock0 = self._receive()["clock"]
        self.cycles = 0
        self._offset = 0
        self._expects = None

    def _receive(self):
        line = self._stream.readline()
        if not line:
            raise SimulationError(f"the Verilator simulation ended unexpectedly; see {self.log_path}")
        return json.loads(line)

    def submit(self, pieces):
        """Start a batch: ``pieces`` = per board of this harness (start, words) or None; the
        same start means the same words (one copy in the command memory)."""
        words_in_file = {}
        for piece in pieces:
            if piece is not None:
                words_in_file[piece[0]] = piece[1]
        with open(self._commands, "w") as f:
            for start in sorted(words_in_file):
                f.write("\n".join(format(w, "x") for w in words_in_file[start]))
                f.write("\n")
        bases = [p[0] if p is not None else 0 for p in pieces]
        counts = [len(p[1]) if p is not None else 0 for p in pieces]
        self._expects = [_results_owed(p[1], self._op) if p is not None else 0 for p in pieces]
        self._stream.write(json.dumps({"bases": bases, "counts": counts, "expects": self._expects}).encode() + b"\n")
        self._stream.flush()

    def collect(self):
        """Wait for the batch; return each board's result words."""
        answer = self._receive()
        self.cycles = answer["clock"] - self._clock0
        out = [[] for _ in self._expects]
        with open(self._results, "rb") as f:
            f.seek(self._offset)
            data = f.read()
        self._offset += len(data)
        for line in data.splitlines():
            b, word = line.split()
            out[int(b)].append(int(word, 16))
        for b, n in enumerate(self._expects):
            if len(out[b]) != n:
                raise SimulationError(f"board {b} sent {len(out[b])} results, the protocol says {n}")
        return out

    def close(self):
        if self._sock is None:
            return
        try:
            self._stream.write(b'{"quit": true}\n')
            self._stream.flush()
        except OSError:
            pass
        self._finalizer()
        self._sock = None
        self._logfile.close()
        return self._proc.returncode


class VerilatorTransport(Transport):
    """The P boards' Verilog under Verilator + cocotb: ``P / per_process`` simulator processes,
    each a harness of ``per_process`` boards (sim/rtl_harness.py), started once and kept running.

    Per call the host writes each simulator's command words as a ``$readmemh`` file, sends it one
    line over a localhost socket (the cocotb control plane), lets all simulators run at once and
    reads their result logs when they answer. Batches larger than the command memory (``depth``
    words) are split: a board's stream may pause between pieces (stall cycles, not board cycles).
    One board per process (the default) is fastest: the P boards share one small build and the
    operating system spreads the processes over the cores (8 boards inlined in one model ran
    16x slower than one board, not 8x). ``vcd``: build with ``--trace`` and write a waveform of
    every simulator (``FILE`` for the first, ``FILE.1``... for the others; short runs only).
    """

    def __init__(self, params, boards, *, per_process=1, depth=None, vcd=None, startup_timeout=600,
                 build_args=None):
        from .rtl_harness import BUILD_ARGS, DEFAULT_DEPTH, build_harness

        if boards % per_process:
            raise ParameterError(f"{boards} boards do not split into simulators of {per_process}")
        self.params, self.boards = params, boards
        self.protocol = BoardProtocol(params)
        self.depth = depth or DEFAULT_DEPTH
        self._op = _op_reader(self.protocol)
        t0 = time.perf_counter()
        self.build = build_harness(params, per_process, depth=self.depth, trace=vcd is not None,
                                   build_args=build_args or BUILD_ARGS)
        self.build_seconds = time.perf_counter() - t0
        self.workdir = Path(tempfile.mkdtemp(prefix="blockray_rtl_"))
        self.per_process = per_process
        self._sims = []
        t0 = time.perf_counter()
        try:
            for k in range(boards // per_process):
                wave = None if vcd is None else (str(vcd) if k == 0 else f"{vcd}.{k}")
                self._sims.append(_HarnessProcess(self.build, self._op, self.workdir / f"sim{k}", vcd=wave,
                                                  startup_timeout=startup_timeout))
        except BaseException:
            self.close()
            raise
        self.start_seconds = time.perf_counter() - t0
        self.cycles = 0
        self.simulator_seconds = 0.0
        self.batches = 0

    def _round(self, pieces):
        t0 = time.perf_counter()
        k = self.per_process
        groups = [pieces[i:i + k] for i in range(0, self.boards, k)]
        active = [any(p is not None for p in g) for g in groups]
        for sim, g, on in zip(self._sims, groups, active):
            if on:
                sim.submit(g)
        out = []
        for sim, g, on in zip(self._sims, groups, active):
            out += sim.collect() if on else [[] for _ in g]
        self.simulator_seconds += time.perf_counter() - t0
        self.batches += 1
        self.cycles = max(sim.cycles for sim in self._sims)
        return out

    def execute(self, batches):
        if len(batches) != self.boards:
            raise ValueError(f"{len(batches)} batches for {self.boards} boards")
        batches = [w if isinstance(w, list) else list(w) for w in batches]
        k = self.per_process
        # within one simulator, one copy of a list shared by several boards; chunks of `share` words
        out = [[] for _ in batches]
        pos = [0] * self.boards
        while True:
            pieces = [None] * self.boards
            busy = False
            for g in range(0, self.boards, k):
                members = range(g, g + k)
                distinct = {id(batches[b]) for b in members if pos[b] < len(batches[b])}
                if not distinct:
                    continue
                share = max(1, self.depth // len(distinct))
                start, placed = 0, {}
                for b in members:
                    words = batches[b]
                    if pos[b] >= len(words):
                        continue
                    key = (id(words), pos[b])
                    if key not in placed:
                        placed[key] = (start, words[pos[b]:pos[b] + share])
                        start += len(placed[key][1])
                    pieces[b] = placed[key]
                busy = True
            if not busy:
                return out
            for b, piece in enumerate(pieces):
                if piece is not None:
                    pos[b] += len(piece[1])
            for b, res in enumerate(self._round(pieces)):
                out[b] += res

    def close(self):
        codes = [sim.close() for sim in self._sims]
        self._sims = []
        if codes and all(c == 0 for c in codes):
            shutil.rmtree(self.workdir, ignore_errors=True)


def _serve():
    """Child process: run the cocotb control plane on the built harness (blocks until it ends)."""
    from cocotb_tools.runner import get_runner
    from .cocotb_support import verilator_env

    config = json.loads(sys.argv[1])
    verilator_env()
    sys.path.insert(0, config["module_dir"])
    runner = get_runner("verilator")
    test_args = ["--trace-file", config["vcd"]] if config["vcd"] else []
    runner.test(hdl_toplevel=config["toplevel"], test_module="rtl_cocotb", build_dir=config["build_dir"],
                test_dir=config["test_dir"], extra_env={"BLOCKRAY_RTL_PORT": str(config["port"])},
                plusargs=config["plusargs"], test_args=test_args, waves=bool(config["vcd"]),
                hdl_toplevel_lang="verilog")


# -- the board ----------------------------------------------------------------------------------

class RTLBoard(ModelBoard):
    """P simulated RTL boards behind the host's Board interface.

    ``backend``: ``"verilator"`` or ``"amaranth"`` (or pass ``transport=`` a factory
    ``(params, boards, vcd=) -> Transport``). The board memories are sized for the scene
    (:func:`~blockray.rtl.protocol.fit_params` on the largest partition); a scene whose partition
    does not fit the hardware's memories (``params.patch_depth``, ``voxel_depth``) raises
    :class:`~blockray.errors.CapacityError` before any simulation starts.
    """

    def __init__(self, params=None, *, bits=None, backend="verilator", vcd=None, transport=None, **kw):
        if backend not in BACKENDS and transport is None:
            raise ParameterError(f"RTL board back-end must be one of {', '.join(BACKENDS)}, not {backend!r}")
        super().__init__(params, bits=bits, **kw)
        self.backend = backend
        self.name = backend
        self.vcd = vcd
        self._factory = transport
        self.transport = None
        self.rtl_params = None

    def _make_transport(self, params):
        if self._factory is not None:
            return self._factory(params, params.boards, vcd=self.vcd)
        if self.backend == "amaranth":
            return AmaranthTransport(params, params.boards, vcd=self.vcd)
        return VerilatorTransport(params, params.boards, vcd=self.vcd)

    def load(self, grid):
        if self.quantised is None:
            raise RuntimeError("prepare() before load()")
        p = self.params
        vox, pat, nvox = registration(grid)
        owner = partition_records(vox, pat, p.boards, self.partition)
        records = int(np.bincount(owner, minlength=p.boards).max()) if len(pat) else 0
        check_capacity(p, records=records, voxels=nvox)         # the hardware's memories: before anything runs
        super().load(grid)
        self.rtl_params = fit_params(p, records=records, voxels=nvox)
        self.protocol = BoardProtocol(self.rtl_params)
        self.decoder = ResultDecoder(self.protocol)
        self._encoded = {}
        self._read_counters = self._encode(Command(Op.READ_COUNTERS))
        self.close()
        self.transport = self._make_transport(self.rtl_params)
        batches = [[self._encode(c) for c in self.load_commands(b)] + [self._read_counters]
                   for b in range(p.boards)]
        results = self.transport.execute(batches)
        snap = self._snapshots(results, expect_blocked=0)
        self._last = {name: arr[:, -1] for name, arr in snap.items()}
        self.load_cycles = [int(c) for c in self._last["cycles"]]

    def _encode(self, command):
        word = self._encoded.get(command)
        if word is None:
            word = self._encoded[command] = self.protocol.encode(command)
        return word

    def _snapshots(self, results, *, expect_blocked):
        """Check each board's result kinds (blocked, counters, blocked, ... or counters only) and
        return the counter snapshots as (P, K) arrays per counter."""
        d = self.decoder
        out = {name: [] for name in ("cycles", "tests_issued", "tests_useful")}
        for b, words in enumerate(results):
            if expect_blocked:
                want = [ResultKind.BLOCKED, ResultKind.COUNTERS] * expect_blocked
            else:
                want = [ResultKind.COUNTERS]
            if d.kinds(words) != [int(k) for k in want]:
                raise SimulationError(f"board {b}: result kinds {d.kinds(words)[:8]}... do not follow the commands")
            snaps = words[1::2] if expect_blocked else words
            for name in out:
                out[name].append(d.counter_array(snaps, name))
        return {name: np.stack(v) for name, v in out.items()}

    def run(self, blocks):
        if self.transport is None:
            raise RuntimeError("load() before run()")
        p = self.params
        words = []
        for block in blocks:
            self.check_block(block)
            words += [self._encode(c) for c in self.block_commands(block)]
            words.append(self._read_counters)
        if not blocks:
            return []
        results = self.transport.execute([words] * p.boards)
        snap = self._snapshots(results, expect_blocked=len(blocks))
        # per block and board: board cycles (minus the previous READ_COUNTERS' own cycle), tests
        diff = {}
        for name, arr in snap.items():
            prev = np.concatenate([self._last[name][:, None], arr[:, :-1]], axis=1)
            diff[name] = arr - prev
            self._last[name] = arr[:, -1]
        cycles = diff["cycles"] - 1                                        # (P, K)
        self._add_batch(cycles.sum(axis=1))
        self._issued_b += diff["tests_issued"].sum(axis=1)
        self._useful_b += diff["tests_useful"].sum(axis=1)
        self._blocks += len(blocks)
        self._rays += sum(b.rays for b in blocks)
        ored = [0] * len(blocks)
        for words_b in results:
            for k, w in enumerate(self.decoder.blocked_words(words_b[0::2])):
                ored[k] |= w
        bits = blocked_bits(ored, p.rows, p.cols)
        return [bits[k, :len(bl.receiver_patch), :len(bl.shooter_patch)].copy() for k, bl in enumerate(blocks)]

    def counters(self):
        out = super().counters()
        rp = self.rtl_params
        out["rtl"] = {
            "backend": self.backend,
            "params": None if rp is None else {"rows": rp.rows, "cols": rp.cols, "boards": rp.boards, "bits": rp.bits,
                                               "patch_depth": rp.patch_depth, "voxel_depth": rp.voxel_depth},
            "simulated_clock_cycles": self.simulated_cycles,
            "simulator_seconds": self._transport_stat("simulator_seconds"),
            "batches": self._transport_stat("batches"),
        }
        return out

    def _transport_stat(self, name):
        if self.transport is not None:
            return getattr(self.transport, name, None)
        return getattr(self, "_stats", {}).get(name)

    @property
    def simulated_cycles(self):
        """Clock cycles the simulator ran (load, blocks, counter reads, idle between batches)."""
        if self.transport is not None:
            return int(self.transport.cycles)
        return getattr(self, "_simulated_cycles", 0)

    def close(self):
        """Stop the simulator (``render`` calls this at the end)."""
        if self.transport is not None:
            self._simulated_cycles = int(self.transport.cycles)
            self._stats = {n: getattr(self.transport, n, None) for n in ("simulator_seconds", "batches")}
            self.transport.close()
            self.transport = None

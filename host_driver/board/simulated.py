"""Transports to simulated boards: the board's byte link answered by a simulator.

* :class:`AmaranthTransport`: :class:`~blockray.rtl.core.BoardCore` in the Amaranth simulator,
  driven through the one drive loop (:class:`blockray.sim.drive.StreamHost`), with optional random
  host idle and result back-pressure (bursts included). Small scenes, debugging, waveforms.
* :class:`VerilatorTransport`: ``BoardCore``'s generated Verilog under Verilator, one simulator
  process per board (:class:`blockray.sim.rtl_harness.HarnessProcess`), started once and kept;
  bytes go in through a ``$readmemh`` file and come back through a ``$fwrite`` log, so the
  simulation runs free between host calls (no Python per cycle). :meth:`~VerilatorTransport.expect`
  starts it at once, so the P boards' simulators run concurrently.
* :class:`ModelTransport`: the bit-exact model (:class:`blockray.sim.model.BoardModel`) behind
  the wire format: the driver and the link without RTL (link traffic measurements, fast tests).

All buffer what :meth:`send` gets and simulate when :meth:`recv` needs bytes (the Glasgow
simulation-pipe pattern).
"""

import shutil
import tempfile
import time
from pathlib import Path

from ...cell import Cell
from ...errors import ParameterError
from .transport import Transport, TransportError

__all__ = ["AmaranthTransport", "VerilatorTransport", "ModelTransport"]


class _Buffered(Transport):
    """Received bytes beyond what recv asked for wait in ``_in``."""

    def __init__(self, *, vcd=None):
        super().__init__(vcd=vcd)
        self._in = bytearray()

    def _take(self, count):
        data = bytes(self._in[:count])
        del self._in[:count]
        return data


class AmaranthTransport(_Buffered):
    """One :class:`~blockray.rtl.core.BoardCore` for ``params`` in the Amaranth simulator.

    ``idle`` / ``backpressure``: :class:`~blockray.sim.drive.HostTiming` of the host on the
    command and result byte streams; ``seed`` seeds them. ``vcd``: write a waveform.
    ``max_cycles``: clock cycles without progress after which :meth:`recv` gives up."""

    def __init__(self, params, *, vcd=None, idle=None, backpressure=None, seed=0, max_cycles=None, cell=Cell()):
        from amaranth.hdl import ClockDomain, Module
        from amaranth.sim import Simulator
        from ...rtl.core import BoardCore
        from ...sim.drive import HostTiming, StreamHost, amaranth_cycle

        super().__init__(vcd=vcd)
        self.params = params
        self.core = core = BoardCore(params, cell=cell)
        m = Module()
        m.domains.sync = self._cd = ClockDomain()
        m.submodules.core = core
        self.host = StreamHost(idle=idle or HostTiming(), backpressure=backpressure or HostTiming(), seed=seed)
        self.cycles = 0
        self.max_cycles = max_cycles
        self._reset_request = False
        self._sim = Simulator(m)
        self._sim.add_clock(1e-8)
        cycle = amaranth_cycle

        async def testbench(ctx):
            while True:
                if self._reset_request:
                    ctx.set(core.i_bytes.valid, 0)
                    ctx.set(core.o_bytes.ready, 0)
                    ctx.set(self._cd.rst, 1)
                    await ctx.tick()
                    ctx.set(self._cd.rst, 0)
                    self.cycles += 1
                    self._reset_request = False
                    continue
                byte = await cycle(ctx, self.host, core.i_bytes, core.o_bytes)
                self.cycles += 1
                if byte is not None:
                    self._in.append(byte)

        self._sim.add_testbench(testbench)
        self._vcd = None
        if vcd is not None:
            self._vcd = self._sim.write_vcd(str(vcd))
            self._vcd.__enter__()
        self.simulator_seconds = 0.0

    def send(self, data):
        self.host.send(bytes(data))

    def recv(self, count, *, timeout=None):
        t0 = time.perf_counter()
        # a board that has all its commands and sends nothing for longer than any command takes
        # (a VOXEL streams at most patch_depth records) has stopped: an error, not a hang
        patience = self.max_cycles or self.params.patch_depth + 4096
        progress = (self.cycles, len(self._in), len(self.host.queue))
        while len(self._in) < count:
            self._sim.advance()
            now = (len(self._in), len(self.host.queue))
            if now != progress[1:] or not self.host.idle:
                progress = (self.cycles,) + now
            elif self.cycles - progress[0] > patience:
                raise TransportError(f"the simulated board sent {len(self._in)} of {count} result bytes and "
                                     f"then nothing for {patience} cycles")
            if timeout is not None and time.perf_counter() - t0 > timeout:
                raise TransportError(f"the simulated board sent {len(self._in)} of {count} bytes in {timeout} s")
        self.simulator_seconds += time.perf_counter() - t0
        return self._take(count)

    def reset(self):
        self.host.reset()
        self._in.clear()
        self._reset_request = True
        while self._reset_request:
            self._sim.advance()

    def stats(self):
        return {"simulated_clock_cycles": self.cycles, "simulator_seconds": self.simulator_seconds}

    def close(self):
        if self._vcd is not None:
            self._vcd.__exit__(None, None, None)
            self._vcd = None


class VerilatorTransport(_Buffered):
    """One board's Verilog under Verilator + cocotb, in its own simulator process (see the module
    docstring). ``depth``: command-memory bytes (longer sends go in pieces; the board's stream
    pauses between them: stalls, not board cycles). ``vcd``: build with ``--trace`` and write a
    waveform (short runs only)."""

    def __init__(self, params, *, vcd=None, depth=None, startup_timeout=600, build_args=None, cell=Cell()):
        from ...sim.rtl_harness import BUILD_ARGS, DEFAULT_DEPTH, HarnessProcess, build_harness

        super().__init__(vcd=vcd)
        self.params = params
        self.depth = depth or DEFAULT_DEPTH
        t0 = time.perf_counter()
        self.build = build_harness(params, 1, depth=self.depth, trace=vcd is not None,
                                   build_args=build_args or BUILD_ARGS, cell=cell)
        self.build_seconds = time.perf_counter() - t0
        self.workdir = Path(tempfile.mkdtemp(prefix="blockray_rtl_"))
        t0 = time.perf_counter()
        self._sim = HarnessProcess(self.build, self.workdir, vcd=vcd, startup_timeout=startup_timeout)
        self.start_seconds = time.perf_counter() - t0
        self._out = bytearray()
        self._inflight = False
        self.simulator_seconds = 0.0
        self.batches = 0

    @property
    def cycles(self):
        return self._sim.cycles

    def send(self, data):
        self._out += data

    def expect(self, count):
        self._flush(count)

    def _flush(self, count):
        """Run what was sent, in pieces of ``depth`` bytes, until ``count`` more result bytes
        came (the earlier pieces owe nothing; what they bring counts)."""
        self._collect()
        before = len(self._in)
        while len(self._out) > self.depth:
            piece = bytes(self._out[:self.depth])
            del self._out[:self.depth]
            self._sim.submit([piece], [0])
            self._inflight = True
            self._collect()
        self._sim.submit([bytes(self._out)], [max(0, count - (len(self._in) - before))])
        self._out.clear()
        self._inflight = True

    def _collect(self):
        if self._inflight:
            t0 = time.perf_counter()
            self._in += self._sim.collect()[0]
            self.simulator_seconds += time.perf_counter() - t0
            self.batches += 1
            self._inflight = False

    def recv(self, count, *, timeout=None):
        if len(self._in) < count and not self._inflight:
            self._flush(count - len(self._in))
        self._collect()
        if len(self._in) < count:
            raise TransportError(f"the Verilator board sent {len(self._in)} of {count} result bytes")
        return self._take(count)

    def reset(self):
        self._collect()
        self._out.clear()
        self._in.clear()
        self._sim.reset()

    def stats(self):
        return {"simulated_clock_cycles": int(self.cycles), "simulator_seconds": self.simulator_seconds,
                "batches": self.batches}

    def close(self):
        if self._sim is None:
            return
        code = self._sim.close()
        self._sim = None
        if code == 0:
            shutil.rmtree(self.workdir, ignore_errors=True)


class ModelTransport(_Buffered):
    """The bit-exact model behind the link: decodes the command bytes, runs
    :meth:`BoardModel.execute <blockray.sim.model.BoardModel.execute>`, encodes its results.
    Counter snapshots are cumulative since the last reset, as the board's; ``stalls`` is 0 (the
    model has no host timing). It makes rays on the board (IDENTIFY answers
    :data:`~blockray.protocol.RAYS_VERSION`): the commands of :mod:`blockray.board_rays` go through
    the block sequencer's model (:class:`~blockray.sim.sequencer.BlockSequencer`). ``rays=False``:
    IDENTIFY answers as a board built without the sequencer does (:data:`~blockray.protocol.VERSION`;
    the host then sends it no ray commands)."""

    def __init__(self, params, *, vcd=None, cell=Cell(), rays=True):
        import functools

        from ...board_rays import RayProtocol
        from ...protocol import BoardProtocol
        from ...sim.model import BoardModel

        if vcd is not None:
            raise ParameterError("the model transport has no waveform", parameter="vcd")
        super().__init__()
        self.params = params
        self.protocol = BoardProtocol(params)
        self._commands = RayProtocol(params)           # decodes both kinds of command
        self._model = functools.partial(BoardModel, cell=cell, rays=rays)
        self._out = bytearray()
        self.reset()

    def send(self, data):
        self._out += data

    def recv(self, count, *, timeout=None):
        if len(self._in) < count and (self._out or self._decoded):
            self._in += self.run()
        if len(self._in) < count:
            raise TransportError(f"the model board sent {len(self._in)} of {count} result bytes")
        return self._take(count)

    def run(self, data=b"", *, whole=True):
        """Take ``data`` after what was sent, execute the complete commands and return their
        result bytes. ``whole=False``: only up to the last READ_COUNTERS or IDENTIFY, later ones
        wait for the next call (the driver ends every batch with one, and the model counts the
        filtered cell's lost cycles per call: so a framed link's pieces run per batch, as
        unframed)."""
        from ...protocol import BoardResult, Op, ResultKind

        self._out += data
        cmds, ends = self._commands.decode_prefix(self._out)
        del self._out[:ends[-1] if ends else 0]
        self._decoded += cmds
        last = len(self._decoded) if whole else 1 + max(
            (k for k, c in enumerate(self._decoded) if c.op in (Op.READ_COUNTERS, Op.IDENTIFY)), default=-1)
        cmds, self._decoded = self._decoded[:last], self._decoded[last:]
        res = self.board.execute(self.sequencer.expand(cmds, self.board))
        out = bytearray()
        for r in res.results:
            if r.kind is ResultKind.COUNTERS:
                c = {k: v + self._base[k] for k, v in r.counters.items()}
                r = BoardResult(r.kind, counters={**c, "stalls": 0})
            out += self.protocol.result_wire(r)
        for name in self._base:
            self._base[name] += getattr(res, name)
        return bytes(out)

    def reset(self):
        from ...sim.sequencer import BlockSequencer
        self.board = self._model(self.params)
        self.sequencer = BlockSequencer(self.params)
        self._base = {"cycles": 0, "busy": 0, "tests_issued": 0, "tests_useful": 0}
        self._out.clear()
        self._decoded = []          # complete commands not yet executed
        self._in.clear()

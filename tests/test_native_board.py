"""The native Verilator harness (sim/native/, host_driver/board/native.py): the board's Verilog clocked
by a C++ loop, the transport of ``--board verilator``.

* RTL = model, bit for bit and cycle for cycle (every counter of the report, the board's cycle
  counters included) on a room of 480 patches (its first shooters; to convergence ``-m slow``);
* the host timing (idle, back-pressure, bursts) is sim/drive.py's from the same seed: the native
  board and the Amaranth simulator driven by StreamHost run the same number of clock cycles and
  answer the same bytes (the oracle shares no code with the C++ loop);
* a missing compiler and a failed build are one-line errors (exit 2 from the CLI);
* identical modules (the array's processors) are one Verilog module and one C++ class
  (sim/native/share.py);
* cornell through the native harness equals the model (``-m slow``).

The RTL boards are a 2 x 2 array, P = 2, B = 10 (tests/test_rtl_board.py's); the build of the
native harness is cached by content (docs/rtl-render.md, "Build").
"""

import re

import numpy as np
import pytest

from blockray.host_driver.cli import main
from blockray.host_driver.scene import builtin
from blockray.host_driver.board.backends import make_board
from blockray.host_driver.render.render import render
from blockray.params import BoardParams
from blockray.sim.drive import HostTiming
from blockray.sim.native import NativeBuildError, Ports, build_native
from blockray.sim.native.share import share_modules

from scenes import COUNTER_KEYS, RTL_BITS as BITS, RTL_PARAMS as PARAMS, room_obj, room_scene, shooter_blocks


#: shooters of the room rendered in the default suite (to convergence: 2255, 17.8 M board cycles)
SHOTS = 20


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return room_scene(tmp_path_factory.mktemp("native_room"), 0.5)


def _same_render(got, model):
    assert np.array_equal(got.radiosity, model.radiosity), "radiosity differs from the model"
    for key in COUNTER_KEYS:
        assert got.report[key] == model.report[key], f"{key}: RTL {got.report[key]}, model {model.report[key]}"


@pytest.mark.cocotb
def test_a_room_of_a_few_hundred_patches_renders_as_the_model(room):
    """Rows end at points drawn per pair (--end-points draw), so the RTL loads other points than
    the centroids it would compute itself."""
    kw = dict(params=PARAMS, bits=BITS, samples=4, voxels=4, max_shots=SHOTS, end_points="draw", end_seed=11)
    model = render(room, backend="model", **kw)
    got = render(room, backend="verilator", **kw)
    print(f"{room.patches} patches, {model.report['shots']} shots, {model.report['blocks']} blocks, "
          f"{model.report['board_cycles']} board cycles")
    assert room.patches >= 200 and model.report["shots"] == SHOTS
    _same_render(got, model)
    transports = got.report["driver"]["transports"]
    assert got.report["driver"]["backend"] == "verilator"
    # every board cycle the model counts was clocked through the C++ loop
    for b, t in enumerate(transports):
        assert t["simulated_clock_cycles"] >= (model.report["board_cycles_per_board"][b]
                                               + model.report["load_cycles_per_board"][b])
        # the board's thread CPU time: spent, and none of it outside the render's run
        assert 0 < t["simulator_cpu_seconds"] <= got.report["cpu_seconds"]["total"]


@pytest.mark.slow
@pytest.mark.cocotb
def test_the_room_to_convergence_renders_as_the_model(room):
    kw = dict(params=PARAMS, bits=BITS, samples=4, voxels=4)
    model = render(room, backend="model", **kw)
    _same_render(render(room, backend="verilator", **kw), model)
    assert model.report["shots"] > room.patches


@pytest.mark.cocotb
def test_host_timing_is_the_drive_loops_cycle_for_cycle(scene_small, rng_seed):
    seed = rng_seed
    host = (HostTiming(0.3, burst=0.004, burst_length=(16, 120)),
            HostTiming(0.25, burst=0.004, burst_length=(16, 120)), seed)
    runs = {}
    shooters = np.random.default_rng(seed).choice(scene_small.patches, 2, replace=False)
    for backend in ("amaranth", "verilator"):
        board = make_board(backend, PARAMS, host=host)
        try:
            blocks = shooter_blocks(scene_small, board, shooters)[:16]          # the Amaranth simulator is slow
            bits = board.run(blocks[:len(blocks) // 2]) + board.run(blocks[len(blocks) // 2:])
            runs[backend] = (bits, board.counters(), [t.stats()["simulated_clock_cycles"] for t in board.transports])
        finally:
            board.close()
    (abits, acounters, acycles), (nbits, ncounters, ncycles) = runs["amaranth"], runs["verilator"]
    assert len(abits) == len(nbits) > 0 and all((a == n).all() for a, n in zip(abits, nbits))
    for key in COUNTER_KEYS:
        assert ncounters[key] == acounters[key], f"{key}: native {ncounters[key]}, amaranth {acounters[key]}"
    # the stalls made the clock run longer than the board's own cycles, by the same count on both
    assert ncycles == acycles, f"clock cycles: native {ncycles}, amaranth {acycles}"
    assert min(acycles) > max(acounters["board_cycles_per_board"]) + max(acounters["load_cycles_per_board"])


@pytest.mark.cocotb
@pytest.mark.parametrize("stalls", [False, True])
def test_reset_is_the_amaranth_transports_cycle_for_cycle(stalls):
    """A reset right after the board opens and one while command bytes are queued and a byte is
    on the wire (the build registers the board's reset: sim/native/share.py, register_reset):
    the native board answers the same bytes as the Amaranth simulator after the same clock
    cycles, its counters restart, and the queued commands are lost."""
    from blockray.host_driver.board.native import NativeTransport
    from blockray.host_driver.board.simulated import AmaranthTransport
    from blockray.protocol import BoardProtocol, Identify, ReadCounters, ResultKind, Voxel

    proto = BoardProtocol(PARAMS)
    nc = proto.result_bytes(ResultKind.COUNTERS)
    host = dict(idle=HostTiming(0.3, burst=0.01, burst_length=(4, 40)),
                backpressure=HostTiming(0.3, burst=0.01, burst_length=(4, 40)), seed=7) if stalls else {}
    runs = {}
    for name, cls in (("amaranth", AmaranthTransport), ("native", NativeTransport)):
        t = cls(PARAMS, **host) if name == "amaranth" else cls(PARAMS, records=False, **host)
        try:
            t.reset()                                   # before any cycle
            t.send(proto.encode_all([Voxel(0), Voxel(1), ReadCounters()] + [Voxel(2)] * 40 + [ReadCounters()]))
            first = t.recv(nc)                          # the rest stays queued, a byte on the wire
            t.reset()
            t.send(proto.encode_all([Voxel(3), Identify(), ReadCounters()]))
            ident = proto.decode_result(t.recv(proto.result_bytes(ResultKind.IDENTITY))).identity
            after = t.recv(nc)
            runs[name] = (first, after, t.stats()["simulated_clock_cycles"], ident)
        finally:
            t.close()
    (afirst, aafter, acycles, aident), (nfirst, nafter, ncycles, nident) = runs["amaranth"], runs["native"]
    assert proto.decode_result(nfirst).counters["cycles"] == 2             # two empty voxels, one bubble each
    assert proto.decode_result(nafter).counters["cycles"] == 2             # VOXEL 3 and IDENTIFY: restarted
    assert {k: v for k, v in nident.items() if k != "version"} == {k: v for k, v in aident.items() if k != "version"}
    assert (nfirst, nafter) == (afirst, aafter)
    assert ncycles == acycles, f"clock cycles: native {ncycles}, amaranth {acycles}"


@pytest.mark.cocotb
def test_records_answer_as_the_bytes_in_fewer_clock_cycles(rng_seed):
    """A quiet host's commands go to the board as whole records (sim/native/harness.cpp,
    ``BoardCore(records=True)``): random memory writes, blocks and counter reads answer the same
    results (the board cycles and every counter but ``stalls``, the link's) as over the byte
    stream, in fewer clock cycles; a stream cut inside a command waits for its rest; an unknown opcode (dropped by the
    board) sends it and the rest over the byte stream; after a reset, records again."""
    from blockray.host_driver.board.native import NativeTransport
    from blockray.protocol import (BeginBlock, BoardProtocol, EndBlock, Identify, LoadPoints, ReadCounters, ResultKind,
                                   Voxel, WritePatch, WriteVoxel)
    from blockray.records import patch_layout

    seed = rng_seed
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    proto = BoardProtocol(PARAMS)
    top, depth = 1 << PARAMS.bits, 40
    point = lambda: tuple(int(c) for c in rng.integers(0, top, 3))              # noqa: E731
    patches = [WritePatch(a, int.from_bytes(rng.bytes(32), "little") % (1 << patch_layout(PARAMS.bits).size))
               for a in range(depth)]
    table = [WriteVoxel(v, int(s), int(rng.integers(0, depth - s + 1))) for v, s in enumerate(rng.integers(0, depth, 8))]

    def blocks(n):
        out = []
        for _ in range(n):
            slots = [(bool(rng.integers(2)), int(rng.integers(2)), point()) for _ in range(int(rng.integers(1, 5)))]
            out += [BeginBlock(), LoadPoints(tuple(slots))] + [Voxel(int(v)) for v in rng.integers(0, 8, 3)] + [EndBlock()]
        return out

    length = {EndBlock: ResultKind.BLOCKED, ReadCounters: ResultKind.COUNTERS, Identify: ResultKind.IDENTITY}
    answers = lambda cs: sum(proto.result_bytes(length[type(c)]) for c in cs if type(c) in length)    # noqa: E731
    first = [Identify()] + patches + table + [ReadCounters()] + blocks(12) + [ReadCounters()]
    wire = proto.encode_all(first)
    cut = len(proto.encode_all(first[:-3])) + 1                 # after the header of the last block's last VOXEL
    done, _ = proto.decode_prefix(wire[:cut])
    second = blocks(6) + [ReadCounters()]
    third = blocks(5) + [ReadCounters()]
    runs = {}
    for records in (True, False):
        t = NativeTransport(PARAMS, records=records)
        try:
            t.send(wire[:cut])
            got = t.recv(answers(done))                         # the board waits for the rest of the command
            t.send(wire[cut:])
            got += t.recv(answers(first) - answers(done))
            t.send(proto.encode_all(second[:3]) + bytes([0x0F]) + proto.encode_all(second[3:]))
            got += t.recv(answers(second))
            t.reset()
            t.send(proto.encode_all(patches + table + third))
            got += t.recv(answers(third))
            runs[records] = (got, t.stats()["simulated_clock_cycles"])
        finally:
            t.close()
    (rgot, rcycles), (bgot, bcycles) = runs[True], runs[False]

    def results(data):              # the stalls counter counts the link's clock cycles: not the board's
        out = [proto.decode_result(r) for r in proto.reader().feed(data)]
        return [r.counters | {"stalls": None} if r.kind is ResultKind.COUNTERS else r for r in out]

    assert len(rgot) == len(bgot) and results(rgot) == results(bgot)
    assert results(rgot)[-1]["cycles"] > 0
    assert rcycles < bcycles, f"clock cycles: records {rcycles}, bytes {bcycles}"


@pytest.fixture(scope="module")
def scene_small(rtl_room):
    return rtl_room


def test_identical_modules_are_one_module_marked_for_verilator():
    from amaranth.hdl import Cat, Module
    from amaranth.lib import wiring
    from amaranth.lib.wiring import In, Out

    from blockray import hdl

    class Count(wiring.Component):
        def __init__(self, width):
            super().__init__({"en": In(1), "n": Out(width)})

        def elaborate(self, platform):
            m = Module()
            with m.If(self.en):
                m.d.sync += self.n.eq(self.n + 1)
            return m

    class Group(wiring.Component):
        """Its cells, enabled together, their counts side by side. A group of one cell has no
        logic of its own: its clock only passes to its submodule."""

        def __init__(self, *cells):
            self.cells = cells
            super().__init__({"en": In(1), "n": Out(sum(len(c.n) for c in cells))})

        def elaborate(self, platform):
            m = Module()
            for name, cell in zip("abcde", self.cells):
                m.submodules[name] = cell
            m.d.comb += [*(c.en.eq(self.en) for c in self.cells), self.n.eq(Cat(*(c.n for c in self.cells)))]
            return m

    top = Group(Count(4), Count(4), Count(5), Group(Count(4)), Group(Count(4)))
    verilog = share_modules(hdl.convert(top, name="top", emit_src=False))
    modules = re.findall(r"^module (\\\S+|\w+)", verilog, re.M)
    # d.a and e.a are a's twins; then d and e are the same text too
    assert modules == ["top", "\\top.a", "\\top.c", "\\top.d"], modules
    assert re.findall(r"^  (\\top\.\w) +(\w+) \(", verilog, re.M) == [
        ("\\top.a", "a"), ("\\top.a", "b"), ("\\top.c", "c"), ("\\top.d", "d"), ("\\top.d", "e"),
        ("\\top.a", "a")]
    text = {name: verilog.split(f"module {name} ")[1].split("endmodule")[0] for name in modules[1:]}
    assert "/* verilator no_inline_module */" in text["\\top.a"] and "  input en /*verilator public*/;" in text["\\top.a"]
    assert "  input clk;" in text["\\top.a"]              # a clock is not copied (sim/native/share.py)
    assert "/* verilator no_inline_module */" in text["\\top.d"] and "public" not in text["\\top.d"]
    assert "verilator" not in text["\\top.c"]


@pytest.mark.cocotb
def test_the_tops_reset_is_a_register_loaded_from_a_new_port():
    """register_reset: the top's rst is a register of the top loaded from rst_d at each edge of
    its clock (the submodules' rst still connects to it); a top without that reset is refused."""
    from amaranth.hdl import Module
    from amaranth.lib import wiring
    from amaranth.lib.wiring import In, Out

    from blockray import hdl
    from blockray.sim.native.share import register_reset

    class Count(wiring.Component):
        en: In(1)
        n: Out(4)

        def elaborate(self, platform):
            m = Module()
            m.submodules.inner = inner = Inner()
            m.d.comb += [inner.en.eq(self.en), self.n.eq(inner.n)]
            return m

    class Inner(wiring.Component):
        en: In(1)
        n: Out(4)

        def elaborate(self, platform):
            m = Module()
            with m.If(self.en):
                m.d.sync += self.n.eq(self.n + 1)
            return m

    verilog = hdl.convert(Count(), name="top", emit_src=False)
    out = register_reset(verilog, "top")
    top = out[out.index("module top("):]
    top = top[:top.index("endmodule")]
    assert re.match(r"module top\([^)]*\brst_d\b", top) and not re.search(r"\(([^)]*, )?rst[,)]", top.splitlines()[0])
    assert "  input rst_d;\n  reg rst = 1'h0;\n  always @(posedge clk)\n    rst <= rst_d;\n" in top
    assert "  input rst;" not in top and "  wire rst;" not in top and ".rst(rst)" in top
    inner = out[out.index("module \\top.inner"):]
    assert "  input rst;" in inner[:inner.index("endmodule")]          # only the top changes
    with pytest.raises(ValueError, match="no reset input"):
        register_reset(verilog, "top", rst="reset")


def test_the_boards_processors_are_one_cpp_class():
    """Verilator kept the processor module that share_modules made one (not inlined per instance)."""
    from blockray.host_driver.board.native import native_build

    obj = native_build(PARAMS).build_dir / "obj"
    assert [p.name for p in obj.glob("Vboard_*processor*.h")] == ["Vboard_board__02eboard__02earray__02eprocessor_0_0.h"]


def test_the_board_is_clocked_with_one_eval_a_cycle():
    """The board's sampled ports are registered: its build runs one eval a clock cycle (the
    comparisons with the Amaranth simulator above run through it); a port the input phase writes,
    or another trigger, keeps two."""
    from dataclasses import replace

    from blockray.host_driver.board.native import native_build
    from blockray.sim.native import SINGLE_EVAL, Ports, single_eval_allowed

    build = native_build(PARAMS)
    assert (build.build_dir / SINGLE_EVAL).exists()
    obj = build.build_dir / "obj"
    ports = Ports(records="i_records")
    assert single_eval_allowed(obj, ports)
    assert not single_eval_allowed(obj, replace(ports, clk="other_clk"))
    bodies = [m.group(1).split("// Body", 1)[-1] for cpp in sorted(obj.glob("*.cpp"))
              for m in re.finditer(r"_ico_sequent\w*\([^)\n]*\)\s*\{\n(.*?)^\}", cpp.read_text(), re.M | re.S)]
    written = next(m.group(1) for body in bodies for m in [re.search(r"[\s.](\w+) = ", body)] if m)

    class Written(Ports):               # a signal the input phase writes, as if it were sampled
        def sampled(self):
            return [written]

    assert not single_eval_allowed(obj, Written(records="i_records"))


def test_a_missing_compiler_is_a_one_line_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("CXX", str(tmp_path / "no-such-g++"))
    monkeypatch.setenv("BLOCKRAY_CACHE_DIR", str(tmp_path / "cache"))
    code = main(["render", str(room_obj(tmp_path)), "--board", "verilator", "--rows", "2", "--cols", "2",
                 "--boards", "2", "--max-shots", "1", "--quiet"])
    lines = [line for line in capsys.readouterr().err.splitlines() if "warning:" not in line]
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith("blockray: error:") and "no-such-g++" in lines[0] and "C++ compiler" in lines[0]


@pytest.mark.slow
def test_a_failed_build_is_a_one_line_error_naming_its_log(tmp_path):
    from amaranth.hdl import Module
    from amaranth.lib import stream, wiring
    from amaranth.lib.fifo import SyncFIFOBuffered
    from amaranth.lib.wiring import In, Out

    class Echo(wiring.Component):
        """A byte FIFO between two byte streams: the harness's ports, clocked."""
        i_bytes: In(stream.Signature(8))
        o_bytes: Out(stream.Signature(8))

        def elaborate(self, platform):
            m = Module()
            m.submodules.fifo = fifo = SyncFIFOBuffered(width=8, depth=4)
            wiring.connect(m, wiring.flipped(self.i_bytes), fifo.w_stream)
            wiring.connect(m, fifo.r_stream, wiring.flipped(self.o_bytes))
            return m

    with pytest.raises(NativeBuildError) as e:
        build_native(Echo(), name="echo", ports=Ports(i_valid="no_such_port"), cache=tmp_path)
    message = str(e.value)
    assert len(message.splitlines()) == 1 and "failed" in message
    log = message.rsplit("see ", 1)[1]
    assert "no_such_port" in open(log).read()


@pytest.mark.slow
@pytest.mark.cocotb
def test_cornell_renders_as_the_model():
    scene = builtin.load("cornell")
    model = render(scene, backend="model", params=BoardParams(bits=None))
    got = render(scene, backend="verilator", params=BoardParams(bits=None))
    _same_render(got, model)
    assert got.report["board_cycles"] == model.report["board_cycles"] > 10 ** 6

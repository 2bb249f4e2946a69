"""Full radiosity runs through the host driver and simulated boards (host_driver/board/driver.py over
the transports of host_driver/board/simulated.py).

A small scene goes through every back-end (golden, model, amaranth, verilator): the simulated RTL
must give the model's blocked bits, per-patch radiosity to the last bit and counters exactly; the
golden float64 board must agree with them to within the quantisation. The RTL boards are a 2 x 2
array, P = 2, B = 10 (the Verilator build of a one-board harness is cached by content; the first
run builds it in about 25 s). The Verilator waveform test (a second, traced build) is ``-m slow``.
"""

import json
import random

import numpy as np
import pytest

from blockray.host_driver.cli import main
from blockray.errors import CapacityError
from blockray.host_driver.board.backends import make_board
from blockray.host_driver.board.driver import BoardDriver, blocked_bits
from blockray.host_driver.render.render import render
from blockray.host_driver.board.simulated import ModelTransport
from blockray.host_driver.board.transport import TransportError
from blockray.host_driver.traverse.voxel import VoxelGrid
from blockray.params import BoardParams
from blockray.protocol import MAGIC, BoardResult, ResultKind
from blockray.samples import SampleScheme
from blockray.sim.drive import HostTiming
from blockray.sim.model import ModelBoard

from scenes import COUNTER_KEYS, RTL_BITS as BITS, RTL_PARAMS as PARAMS, room_scene, shooter_blocks

@pytest.fixture(scope="module")
def scene(rtl_room):
    return rtl_room


def _render(scene, board, vcd=None):
    return render(scene, backend=board, params=PARAMS, bits=None if board == "golden" else BITS,
                  samples=4, max_shots=2, voxels=3, vcd=vcd)


@pytest.fixture(scope="module")
def renders(scene, tmp_path_factory):
    vcd = tmp_path_factory.mktemp("vcd") / "amaranth.vcd"
    out = {name: _render(scene, name, vcd=vcd if name == "amaranth" else None)
           for name in ("golden", "model", "model-link", "amaranth", "verilator")}
    out["vcd"] = vcd
    return out


@pytest.mark.cocotb
def test_every_backend_renders_the_small_scene(scene, renders):
    model = renders["model"]
    print(f"{scene.patches} patches, {model.report['blocks']} blocks, {model.report['board_cycles']} board cycles")
    assert model.report["blocks"] > 20 and scene.patches > 30
    for name in ("model-link", "amaranth", "verilator"):
        got = renders[name]
        assert got.report["board"] == name
        assert np.array_equal(got.radiosity, model.radiosity), f"{name}: radiosity differs from the model"
        for key in COUNTER_KEYS:
            assert got.report[key] == model.report[key], f"{name}: {key} {got.report[key]} != model {model.report[key]}"
        driver = got.report["driver"]
        assert driver["backend"] == name
        # the memories are sized for the scene's partition
        assert driver["params"]["patch_depth"] == max(model.report["load_cycles_per_board"]) - 27
        assert driver["params"]["voxel_depth"] == 27
        # the same bytes on every link, whatever answers them
        assert got.report["link"] == renders["model-link"].report["link"]
        if name == "model-link":
            continue
        # every board cycle was simulated: each board ran its load and its blocks; through the
        # Amaranth simulator the bytes of every command crossed the link one per clock cycle, the
        # native harness handed the board whole command records (sim/native/harness.cpp)
        for b, t in enumerate(driver["transports"]):
            assert t["simulated_clock_cycles"] >= (model.report["board_cycles_per_board"][b]
                                                   + model.report["load_cycles_per_board"][b])
        clock = sum(t["simulated_clock_cycles"] for t in driver["transports"])
        assert clock >= got.report["link"]["bytes_sent"] if name == "amaranth" else clock < got.report["link"]["bytes_sent"]
    # the golden float64 board: the same picture up to the quantisation of the scene
    golden = renders["golden"]
    rel = np.abs(golden.radiosity - model.radiosity).max() / model.radiosity.max()
    print(f"golden vs model: max difference {rel:.2e} of the brightest patch")
    assert rel < 0.02


@pytest.mark.cocotb
@pytest.mark.parametrize("backend", ["amaranth", "verilator", "verilator-cocotb"])
def test_blocked_bits_and_block_cycles_equal_the_model(scene, backend):
    seed = 11
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    shooters = rng.choice(scene.patches, 2, replace=False)
    model = ModelBoard(PARAMS)
    blocks = shooter_blocks(scene, model, shooters)
    # the same two batches as the RTL board below: each batch pays its last END_BLOCK's drain
    expect = model.run(blocks[:len(blocks) // 2]) + model.run(blocks[len(blocks) // 2:])
    host = (HostTiming(0.2, burst=0.003, burst_length=(30, 200)),
            HostTiming(0.3, burst=0.003, burst_length=(30, 200)), seed) if backend != "verilator-cocotb" else None
    if backend == "verilator-cocotb":          # the cocotb route (host_driver/board/simulated.py)
        from blockray.host_driver.board.simulated import VerilatorTransport
        board = BoardDriver(PARAMS, transport=lambda p, b: VerilatorTransport(p))
    else:
        board = make_board(backend, PARAMS, host=host)
    try:
        assert len(shooter_blocks(scene, board, shooters)) == len(blocks)
        if backend == "verilator-cocotb":
            for t in board.transports:
                t.depth = 37                   # the host splits batches anywhere: same results
        # two calls: the counters carry over between batches
        got = board.run(blocks[:len(blocks) // 2]) + board.run(blocks[len(blocks) // 2:])
    finally:
        board.close()
    assert len(got) == len(expect)
    for k, (g, e) in enumerate(zip(got, expect)):
        assert g.shape == e.shape and (g == e).all(), f"block {k}: RTL {g.astype(int).tolist()}, model {e.astype(int).tolist()}"
    blocked = sum(int(e.sum()) for e in expect)
    assert 0 < blocked < sum(e.size for e in expect), "the scene must have blocked and clear rays"
    mc, rc = model.counters(), board.counters()
    for key in COUNTER_KEYS:
        assert rc[key] == mc[key], f"{key}: RTL {rc[key]}, model {mc[key]}"


def test_scene_that_does_not_fit_fails_before_simulation(scene):
    made = []
    small = PARAMS.with_(patch_depth=8)
    board = BoardDriver(small, transport=lambda *a: made.append(a))
    board.prepare(scene, SampleScheme(4))
    grid = VoxelGrid(scene.patch_vertices, 3, margin=board.margin)
    with pytest.raises(CapacityError, match="patch_depth 8"):
        board.load(grid)
    assert made == [], "no simulator may start for a scene that does not fit"


def test_blocked_bits_unpack_the_words():
    seed = 5
    print(f"seed={seed}")
    rng = random.Random(seed)
    words = [rng.getrandbits(15) for _ in range(50)]
    bits = blocked_bits(words, 3, 5)
    for i, w in enumerate(words):
        for r in range(3):
            for s in range(5):
                assert bits[i, r, s] == bool(w >> (r * 5 + s) & 1)


class _Liar(ModelTransport):
    """A model board that answers IDENTIFY with other fields."""

    def __init__(self, params, **fields):
        super().__init__(params)
        self.fields = fields

    def recv(self, count, *, timeout=None):
        data = super().recv(count, timeout=timeout)
        got = self.protocol.decode_result(data)
        if got.kind is ResultKind.IDENTITY:
            data = self.protocol.result_wire(BoardResult(got.kind, identity={**got.identity, **self.fields}))
        return data


@pytest.mark.parametrize("fields,error,match", [
    ({"magic": MAGIC ^ 1}, TransportError, "is not a blockray board"),
    ({"version": 1}, TransportError, "protocol version"),
    ({"rows": 4}, CapacityError, "rows 4 \\(host 2\\)"),
    ({"patch_depth": 7}, CapacityError, "patch_depth 7"),
    ({"cell": 2, "d_bits": 9, "w_bits": 9}, CapacityError, "cell lean d9w9 \\(host exact; (--)?cell\\)$"),
    ({"cell": 1, "d_bits": 15, "w_bits": 18}, CapacityError, "cell filtered d15w18 \\(host exact"),
    ({"cell": 3}, TransportError, "IDENTIFY names cell 3, not one of 0..2"),
])
def test_driver_checks_the_identity(scene, fields, error, match):
    """IDENTIFY comes first: a board of another protocol or configuration is refused before the
    memories are loaded."""
    opened = []

    def transport(params, b):
        opened.append(_Liar(params, **fields) if b == 1 else ModelTransport(params))
        return opened[-1]

    board = BoardDriver(PARAMS, transport=transport)
    board.prepare(scene, SampleScheme(4))
    with pytest.raises(error, match=match):
        board.load(VoxelGrid(scene.patch_vertices, 3, margin=board.margin))
    assert len(opened) == 2 and not opened[0]._out, "nothing but IDENTIFY may have been sent"
    board.close()


@pytest.mark.cocotb
def test_amaranth_vcd(renders):
    """The amaranth render above wrote a waveform of each board (FILE, FILE.1) for the whole run,
    through temporaries beside them (blockray/atomic.py) that are gone."""
    assert sorted(p.name for p in renders["vcd"].parent.iterdir()) == ["amaranth.vcd", "amaranth.vcd.1"]
    for b, path in enumerate((renders["vcd"], renders["vcd"].with_name(renders["vcd"].name + ".1"))):
        text = path.read_text()
        assert "i_bytes__valid" in text and "o_bytes__payload" in text and "commands__valid" in text
        last = max(int(line[1:]) for line in text.splitlines() if line.startswith("#") and line[1:].isdigit())
        cycles = renders["amaranth"].report["driver"]["transports"][b]["simulated_clock_cycles"]
        assert last >= (cycles - 1) * 10_000_000                 # 10 ns clock in fs


@pytest.mark.cocotb
def test_cli_render_verilator(tmp_path, capsys):
    room = room_scene(tmp_path, 1.5)
    del room
    obj = tmp_path / "room.obj"
    report = tmp_path / "r.json"
    argv = ["render", str(obj), "--max-edge", "1.5", "--voxels", "3", "--samples", "4", "--max-shots", "1",
            "--rows", "2", "--cols", "2", "--boards", "2", "--bits", str(BITS), "--quiet"]
    assert main(argv + ["--board", "verilator", "--report", str(report)]) == 0
    assert main(argv + ["--board", "model", "--report", str(tmp_path / "m.json")]) == 0
    got, want = json.loads(report.read_text()), json.loads((tmp_path / "m.json").read_text())
    assert got["board"] == "verilator"
    for key in ("board_cycles", "tests_issued", "tests_useful", "utilization", "board_cycles_per_board"):
        assert got[key] == want[key], key
    # --vcd needs a simulated board
    assert main(argv + ["--board", "model", "--vcd", str(tmp_path / "x.vcd")]) == 2
    assert "--vcd needs a simulated RTL board" in capsys.readouterr().err


def _makes_rays_as_the_model(tmp_path, argv):
    """``blockray render argv --traversal board`` on --board verilator and model: the same CSV
    byte for byte and every counter."""
    argv = argv + ["--boards", "1", "--traversal", "board", "--quiet"]
    for board in ("verilator", "model"):
        assert main(argv + ["--board", board, "--patches", str(tmp_path / f"{board}.csv"),
                            "--report", str(tmp_path / f"{board}.json")]) == 0
    got, want = (json.loads((tmp_path / f"{b}.json").read_text()) for b in ("verilator", "model"))
    assert want["blocks"] > 20
    for key in COUNTER_KEYS:
        assert got[key] == want[key], key
    assert (tmp_path / "verilator.csv").read_bytes() == (tmp_path / "model.csv").read_bytes()


@pytest.mark.cocotb
def test_cli_render_verilator_makes_rays(tmp_path):
    """--traversal board on the Verilated board, whose deframer feeds the block sequencer: the
    room of the RTL tests on a 2 x 2 board at B = 10."""
    room_scene(tmp_path, 1.5)
    _makes_rays_as_the_model(tmp_path, ["render", str(tmp_path / "room.obj"), "--max-edge", "1.5", "--voxels", "3",
                                        "--samples", "4", "--max-shots", "2", "--rows", "2", "--cols", "2",
                                        "--bits", str(BITS)])


@pytest.mark.slow
@pytest.mark.cocotb
def test_cli_render_verilator_makes_rays_cornell(tmp_path):
    """The same on cornell, the ULX3S default's 1 x 2 board at the CLI's B (18) and grid, two
    shooters (10 080 rays, 307 k board cycles; 45 s with the build)."""
    _makes_rays_as_the_model(tmp_path, ["render", "cornell", "--max-shots", "2", "--rows", "1", "--cols", "2"])


@pytest.mark.slow
@pytest.mark.cocotb
def test_verilator_vcd(scene, tmp_path):
    vcd = tmp_path / "board.vcd"
    render(scene, backend="verilator", params=PARAMS, bits=BITS, samples=4, max_shots=1, voxels=3, vcd=vcd)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["board.vcd", "board.vcd.1"]     # no temporary left
    for path in (vcd, tmp_path / "board.vcd.1"):         # one waveform per simulator process (board)
        text = path.read_text()
        assert "i_bytes__valid" in text and "\n#1" in text


def test_amaranth_transport_reset_and_silence():
    """The transport's reset clears the board (counters restart, queued bytes dropped), and a
    board that owes nothing makes recv fail with a clear error instead of hanging."""
    from blockray.host_driver.board.simulated import AmaranthTransport
    from blockray.protocol import BoardProtocol, Identify, ReadCounters, Voxel
    params = BoardParams(rows=2, cols=2, bits=8, patch_depth=8, voxel_depth=4)
    proto = BoardProtocol(params)
    t = AmaranthTransport(params)
    t.send(proto.encode_all([Voxel(0), Voxel(1), ReadCounters()]))
    first = proto.decode_result(t.recv(proto.result_bytes(ResultKind.COUNTERS))).counters
    assert first["cycles"] == 2                         # two empty voxels, one bubble each
    t.send(proto.encode(Voxel(2)))
    t.reset()                                           # the queued VOXEL is lost with the reset
    t.send(proto.encode_all([Identify(), ReadCounters()]))
    ident = proto.decode_result(t.recv(proto.result_bytes(ResultKind.IDENTITY)))
    assert ident.identity == proto.identity()
    after = proto.decode_result(t.recv(proto.result_bytes(ResultKind.COUNTERS))).counters
    assert after["cycles"] == 1                         # IDENTIFY only: the counters restarted
    with pytest.raises(TransportError, match="then nothing for"):
        t.recv(1)
    t.close()

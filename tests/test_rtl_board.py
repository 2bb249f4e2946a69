"""Full radiosity runs through the simulated RTL board (sim/rtl_board.py).

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

from blockray.cli import main
from blockray.errors import CapacityError
from blockray.host_driver.objload import load_obj
from blockray.host_driver.render import Visibility, render
from blockray.host_driver.voxel import VoxelGrid
from blockray.params import BoardParams
from blockray.rtl.protocol import BoardProtocol, ResultKind
from blockray.samples import SampleScheme
from blockray.sim.model import ModelBoard
from blockray.sim.rtl_board import ResultDecoder, RTLBoard, blocked_bits

from test_render import box_faces, write_obj

PARAMS = BoardParams(rows=2, cols=2, boards=2)
BITS = 10
#: the counters the RTL must reproduce exactly (ModelBoard.counters keys)
COUNTER_KEYS = ("board_cycles", "tests_issued", "tests_useful", "tests", "utilization",
                "board_cycles_per_board", "tests_issued_per_board", "tests_useful_per_board",
                "utilization_per_board", "load_cycles_per_board", "blocks", "rays", "bits")


def room_scene(tmp_path, max_edge):
    """A closed room with one emitting wall and a box that casts shadows."""
    room = box_faces((0, 0, 0), (2, 2, 2), True)
    light, walls = room[3:4], room[:3] + room[4:]
    inner = box_faces((0.6, 0.0, 0.6), (1.4, 0.8, 1.4), False)
    path = write_obj(tmp_path, [("walls", ("white", (0.5,) * 3, (0,) * 3), walls),
                                ("light", ("lamp", (0.5,) * 3, (1,) * 3), light),
                                ("block", ("white", (0.5,) * 3, (0,) * 3), inner)], name="room")
    return load_obj(path, max_edge=max_edge)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return room_scene(tmp_path_factory.mktemp("rtl_scene"), 1.5)


def _render(scene, board, vcd=None):
    return render(scene, board=board, params=PARAMS, bits=None if board == "golden" else BITS,
                  samples=4, max_shots=2, voxels=3, vcd=vcd)


@pytest.fixture(scope="module")
def renders(scene, tmp_path_factory):
    vcd = tmp_path_factory.mktemp("vcd") / "amaranth.vcd"
    out = {name: _render(scene, name, vcd=vcd if name == "amaranth" else None)
           for name in ("golden", "model", "amaranth", "verilator")}
    out["vcd"] = vcd
    return out


@pytest.mark.cocotb
def test_every_backend_renders_the_small_scene(scene, renders):
    model = renders["model"]
    print(f"{scene.patches} patches, {model.report['blocks']} blocks, {model.report['board_cycles']} board cycles")
    assert model.report["blocks"] > 20 and scene.patches > 30
    for name in ("amaranth", "verilator"):
        got = renders[name]
        assert got.report["board"] == name
        assert np.array_equal(got.radiosity, model.radiosity), f"{name}: radiosity differs from the model"
        for key in COUNTER_KEYS:
            assert got.report[key] == model.report[key], f"{name}: {key} {got.report[key]} != model {model.report[key]}"
        rtl = got.report["rtl"]
        assert rtl["backend"] == name
        # the memories are sized for the scene's partition
        assert rtl["params"]["patch_depth"] == max(model.report["load_cycles_per_board"]) - 27
        assert rtl["params"]["voxel_depth"] == 27
        # every board cycle was simulated: each board ran its blocks, a READ_COUNTERS per block and the load
        assert rtl["simulated_clock_cycles"] >= (max(model.report["board_cycles_per_board"]) + model.report["blocks"]
                                                 + max(model.report["load_cycles_per_board"]))
    # the golden float64 board: the same picture up to the quantisation of the scene
    golden = renders["golden"]
    rel = np.abs(golden.radiosity - model.radiosity).max() / model.radiosity.max()
    print(f"golden vs model: max difference {rel:.2e} of the brightest patch")
    assert rel < 0.02


def _blocks(scene, board, shooters):
    board.prepare(scene, SampleScheme(4))
    grid = VoxelGrid(scene.patch_vertices, 3, margin=board.margin)
    board.load(grid)
    vis = Visibility(scene, board, grid, SampleScheme(4), rows=PARAMS.rows, cols=PARAMS.cols)
    blocks = []
    for i in shooters:
        blocks += vis._blocks_for(i, np.arange(scene.patches))
    return blocks


@pytest.mark.cocotb
@pytest.mark.parametrize("backend", ["amaranth", "verilator"])
def test_blocked_bits_and_block_cycles_equal_the_model(scene, backend):
    seed = 11
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    shooters = rng.choice(scene.patches, 2, replace=False)
    model = ModelBoard(PARAMS, bits=BITS)
    blocks = _blocks(scene, model, shooters)
    # the same two batches as the RTL board below: each batch pays its last END_BLOCK's drain
    expect = model.run(blocks[:len(blocks) // 2]) + model.run(blocks[len(blocks) // 2:])
    board = RTLBoard(PARAMS, bits=BITS, backend=backend)
    try:
        assert len(_blocks(scene, board, shooters)) == len(blocks)
        if backend == "verilator":
            board.transport.depth = 37         # the host splits batches anywhere: same results
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
    board = RTLBoard(small, bits=BITS, transport=lambda *a, **k: made.append(a))
    board.prepare(scene, SampleScheme(4))
    grid = VoxelGrid(scene.patch_vertices, 3, margin=board.margin)
    with pytest.raises(CapacityError, match="patch_depth 8"):
        board.load(grid)
    assert made == [], "no simulator may start for a scene that does not fit"


def test_result_decoder_equals_the_protocol():
    seed = 5
    print(f"seed={seed}")
    rng = random.Random(seed)
    params = BoardParams(rows=3, cols=5, bits=12, patch_depth=100, voxel_depth=64)
    proto = BoardProtocol(params)
    dec = ResultDecoder(proto)
    words = [rng.getrandbits(proto.result_layout.size) for _ in range(200)]
    kinds = dec.kinds(words)
    blocked = dec.blocked_words(words)
    for i, w in enumerate(words):
        ref = proto.decode_result(w)
        assert kinds[i] == int(ref.kind)
        if ref.kind is ResultKind.BLOCKED:
            assert blocked[i] == ref.blocked
        else:
            for name, value in ref.counters.items():
                assert dec.counter_array([w], name)[0] == value
    bits = blocked_bits(blocked, 3, 5)
    for i, w in enumerate(blocked):
        for r in range(3):
            for s in range(5):
                assert bits[i, r, s] == bool(w >> (r * 5 + s) & 1)


@pytest.mark.cocotb
def test_amaranth_vcd(renders):
    """The amaranth render above wrote a waveform of both boards for the whole run."""
    text = renders["vcd"].read_text()
    assert "commands__valid" in text and "results__payload" in text and "board1" in text
    last = max(int(line[1:]) for line in text.splitlines() if line.startswith("#") and line[1:].isdigit())
    assert last >= renders["amaranth"].report["rtl"]["simulated_clock_cycles"] * 10_000_000  # 10 ns clock in fs


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


@pytest.mark.slow
@pytest.mark.cocotb
def test_verilator_vcd(scene, tmp_path):
    vcd = tmp_path / "board.vcd"
    render(scene, board="verilator", params=PARAMS, bits=BITS, samples=4, max_shots=1, voxels=3, vcd=vcd)
    for path in (vcd, tmp_path / "board.vcd.1"):         # one waveform per simulator process (board)
        text = path.read_text()
        assert "commands__valid" in text and "\n#1" in text

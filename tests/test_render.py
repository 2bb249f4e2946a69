"""End-to-end: scene file -> CLI/render loop -> board -> solver -> outputs."""

import csv
import json

import numpy as np
import pytest

from blockray.host_driver.cli import main
from blockray.host_driver.scene.objload import load_obj
from blockray.host_driver.render.render import render

from scenes import box_faces, write_obj


RHO, E = 0.5, 1.0


@pytest.fixture
def closed_box(tmp_path):
    path = write_obj(tmp_path, [("box", ("wall", (RHO,) * 3, (E,) * 3), box_faces((0, 0, 0), (1, 1, 1), True))])
    return load_obj(path, max_edge=0.5)


@pytest.mark.parametrize("board", ["golden", "model"])
@pytest.mark.parametrize("solver", ["progressive", "gauss-seidel"])
def test_closed_box_uniform_emission(closed_box, board, solver):
    # Sum_j F_ij = 1 in a closed enclosure, so B = E + rho B: B = E / (1 - rho) on every patch.
    res = render(closed_box, backend=board, solver=solver, tolerance=1e-5, voxels=3)
    expect = E / (1 - RHO)
    err = np.abs(res.radiosity / expect - 1)
    print(f"{board} {solver}: max relative error {err.max():.2e} over {closed_box.patches} patches")
    assert err.max() < 0.01
    assert res.report["rays"] > 0 and res.report["tests"] > 0


def test_energy_balance_with_occluder(tmp_path):
    # A closed room, uniform reflectance, one emitting face, and a box inside that casts shadows.
    # Energy balance: sum A B = sum A E / (1 - rho) whatever the occlusion.
    room = box_faces((0, 0, 0), (2, 2, 2), True)
    light, walls = room[3:4], room[:3] + room[4:]       # the y = 2 face emits
    inner = box_faces((0.6, 0.0, 0.6), (1.4, 0.8, 1.4), False)
    path = write_obj(tmp_path, [("walls", ("white", (RHO,) * 3, (0,) * 3), walls),
                                ("light", ("lamp", (RHO,) * 3, (E,) * 3), light),
                                ("block", ("white", (RHO,) * 3, (0,) * 3), inner)])
    scene = load_obj(path, max_edge=0.5)
    res = render(scene, backend="model", tolerance=1e-4, voxels=4)
    A = scene.areas[:, None]
    lhs = (A * res.radiosity).sum(0)
    rhs = (A * scene.emission).sum(0) / (1 - RHO)
    print("energy balance ratio", lhs / rhs, "blocked rays present:", res.report["tests"])
    assert np.allclose(lhs / rhs, 1, atol=0.03)
    # the block casts a shadow: the floor under it is darker than the floor beside it
    floor = np.flatnonzero(np.abs(scene.centroids[:, 1]) < 1e-9)
    under = floor[(np.abs(scene.centroids[floor, 0] - 1) < 0.35) & (np.abs(scene.centroids[floor, 2] - 1) < 0.35)]
    beside = floor[(np.abs(scene.centroids[floor, 0] - 1) > 0.6)]
    assert len(under) and len(beside)
    assert res.radiosity[under].mean() < 0.9 * res.radiosity[beside].mean()


def test_cli_outputs(tmp_path, closed_box):
    path = write_obj(tmp_path, [("box", ("wall", (RHO,) * 3, (E,) * 3), box_faces((0, 0, 0), (1, 1, 1), True))],
                     name="cli")
    csv_path, json_path, png = tmp_path / "p.csv", tmp_path / "r.json", tmp_path / "i.png"
    rc = main(["render", str(path), "--max-edge", "0.5", "--voxels", "2", "--image", str(png),
               "--patches", str(csv_path), "--report", str(json_path), "--quiet", "--size", "64"])
    assert rc == 0
    rows = list(csv.DictReader(open(csv_path)))
    assert list(rows[0]) == ["patch", "group", "area", "cx", "cy", "cz", "B_r", "B_g", "B_b"]
    assert len(rows) == closed_box.patches
    assert abs(sum(float(r["area"]) for r in rows) - 6.0) < 1e-9
    report = json.loads(json_path.read_text())
    for key in ("scene", "patches", "voxels", "board", "solver", "shots", "rays", "tests", "residual",
                "seconds", "traversal_stats", "board_cycles", "tests_issued", "tests_useful", "utilization"):
        assert key in report, key
    for key in ("l", "n", "L", "overhead"):
        assert key in report["traversal_stats"], key
    assert report["residual"] < 1e-3 and report["board"] == "model"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _run_cli(capsys, argv):
    with pytest.raises(SystemExit) as e:
        raise SystemExit(main(argv))
    err = capsys.readouterr().err
    return e.value.code, err


@pytest.mark.parametrize("obj, mtl, needle", [
    ("mtllib s.mtl\nusemtl m\nv 0 0 0\nv 1 0 0\nv 0 nan 0\nf 1 2 3\n", "newmtl m\nKd 0.5 0.5 0.5\n", "s.obj:5"),
    ("mtllib s.mtl\nusemtl m\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", "newmtl m\nKd 0.5 0.5 0.5\n", "s.obj:6"),
    ("mtllib s.mtl\nusemtl m\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "newmtl m\nKd 1.0 0.5 0.5\n", "s.mtl:2"),
    ("mtllib s.mtl\nusemtl m\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "newmtl m\nKd 0.5 0.5\nKe x 1 1\n", "s.mtl:"),
])
def test_cli_bad_scene_exits_2_with_location(tmp_path, capsys, obj, mtl, needle):
    (tmp_path / "s.obj").write_text(obj)
    (tmp_path / "s.mtl").write_text(mtl)
    code, err = _run_cli(capsys, ["render", str(tmp_path / "s.obj"), "--quiet"])
    assert code == 2
    assert needle in err and err.startswith("blockray: error:") and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("argv, needle", [
    (["render", "/nonexistent/x.obj"], "x.obj"),
    (["render", "cornell", "--bits", "30"], "--bits"),
    (["render", "cornell", "--board", "nonsense"], "--board"),
    (["render", "cornell", "--voxels", "0"], "--voxels"),
    (["render", "cornell", "--max-edge", "-1"], "--max-edge"),
    (["render", "cornell", "--tolerance", "nan"], "--tolerance"),
    (["render", "cornell", "--partition", "stripes"], "--partition"),
    (["render", "cornell", "--board", "golden", "--partition", "patch"], "--partition"),
])
def test_cli_bad_parameters_exit_2(capsys, argv, needle):
    code, err = _run_cli(capsys, argv + ["--quiet"])
    assert code == 2
    assert needle in err and "Traceback" not in err


def _occluded_room(tmp_path):
    room = box_faces((0, 0, 0), (2, 2, 2), True)
    inner = box_faces((0.6, 0.0, 0.6), (1.4, 0.8, 1.4), False)
    path = write_obj(tmp_path, [("walls", ("white", (RHO,) * 3, (0,) * 3), room[:3] + room[4:]),
                                ("light", ("lamp", (RHO,) * 3, (E,) * 3), room[3:4]),
                                ("block", ("white", (RHO,) * 3, (0,) * 3), inner)], name="occluded")
    return load_obj(path, max_edge=0.7)


def test_block_grouping_and_traversal_do_not_change_the_answer(tmp_path):
    # The model board's predicate is exact and every traversal covers each ray's voxels, so how
    # rays are bundled (per-voxel blocks, filled blocks, one ray at a time along its 3D-DDA) must
    # not change one blocked bit: the radiosity is identical to the last bit.
    scene = _occluded_room(tmp_path)
    runs = {}
    for traversal, packing in (("block", "voxel"), ("block", "cube"), ("block", "fill"), ("ray", "voxel")):
        res = render(scene, backend="model", voxels=4, max_shots=6, traversal=traversal, packing=packing)
        runs[traversal, packing] = res
    base = runs["block", "voxel"]
    assert base.report["blocks"] > 0 and base.report["rays"] > 0
    for key, res in runs.items():
        assert res.report["rays"] == base.report["rays"], key
        assert np.array_equal(res.radiosity, base.radiosity), key
    # filling the array's rows needs fewer blocks; one ray per block needs one block per ray
    assert runs["block", "fill"].report["blocks"] <= runs["block", "cube"].report["blocks"] < base.report["blocks"]
    assert runs["ray", "voxel"].report["blocks"] == base.report["rays"]
    # the voxel grid does not matter either, and some rays really are blocked (not vacuous)
    from blockray.sim.model import ModelBoard

    class CountingBoard(ModelBoard):
        blocked = 0

        def run(self, blocks):
            bits = super().run(blocks)
            self.blocked += sum(int(np.sum(b)) for b in bits)
            return bits

    counting = CountingBoard()
    coarse = render(scene, board=counting, voxels=1, max_shots=6)
    assert np.array_equal(coarse.radiosity, base.radiosity)
    print(f"blocked rays: {counting.blocked} of {coarse.report['rays']}")
    assert 0 < counting.blocked < coarse.report["rays"]


def test_gathering_render_returns_the_factors_progressive_refinement_shoots(tmp_path):
    # benchmarks/bench_room_ties.py solves a board's F again (exactly, and by progressive
    # refinement): the F a gathering render returns must be the one it solved with, column for
    # column the one a progressive render shoots, so both solves reproduce the renders to the bit.
    from blockray.host_driver.radiosity import solver as solvers
    scene = _occluded_room(tmp_path)
    gathered = render(scene, backend="model", voxels=4, solver="jacobi", tolerance=1e-8)
    F = gathered.factors
    assert F.shape == (scene.patches, scene.patches) and np.count_nonzero(F == 0) < F.size
    assert np.array_equal(solvers.jacobi(scene, F, tolerance=1e-8).B, gathered.radiosity)
    shot = render(scene, backend="model", voxels=4, max_shots=12)
    assert shot.factors is None
    again = solvers.progressive_refinement(scene, lambda i: F[:, i], max_shots=12)
    assert np.array_equal(again.B, shot.radiosity)


def test_cli_board_parameter_errors_name_the_option(capsys):
    code, err = _run_cli(capsys, ["render", "cornell", "--rows", "200", "--quiet"])
    assert code == 2 and err.startswith("blockray: error: --rows:") and "Traceback" not in err


def test_cli_board_choices_come_from_the_registry(capsys, monkeypatch):
    """--board lists the registry's back-ends (exactly, in order) and their help; an unknown name
    is refused (exit 2) with the choices, and the link-timing options need a board simulated
    cycle by cycle."""
    from blockray.host_driver.board.backends import BACKENDS
    # argparse wraps help to the terminal's width, breaking lines at hyphens too ("model-" /
    # "link"): a terminal too wide to wrap anything keeps each phrase on one line
    monkeypatch.setenv("COLUMNS", "100000")
    with pytest.raises(SystemExit) as e:
        main(["render", "--help"])
    assert e.value.code == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "--board {" + ",".join(BACKENDS) + "}" in out          # the choices, no more, no fewer
    for name, entry in BACKENDS.items():
        assert f"{name} ({' '.join(entry.help.split())})" in out, name
    code, err = _run_cli(capsys, ["render", "cornell", "--board", "nope"])
    assert code == 2 and "invalid choice: 'nope'" in err and "model-link" in err
    code, err = _run_cli(capsys, ["render", "cornell", "--board", "model", "--link-bursts", "0.01", "--quiet"])
    assert code == 2 and "--link-bursts need a board simulated cycle by cycle (--board amaranth or verilator)" in err
    code, err = _run_cli(capsys, ["render", "cornell", "--board", "amaranth", "--link-idle", "1.5", "--quiet"])
    assert code == 2 and err.startswith("blockray: error: --link-idle / --link-backpressure / --link-bursts: host timing rate must be in "
                                  "[0, 1)")


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["cornell", "room"])
def test_model_within_1e_4_of_golden(scene):
    """The fixed-point model's radiosity is within 1e-4 RMS relative of the golden board's on the
    built-in scenes at their default B, in each channel and over all channels, as
    docs/formfactors.md and benchmarks/bench_render.py measure it (room: 15 min of golden)."""
    from blockray.host_driver.scene import builtin
    scene = builtin.load(scene)
    golden = render(scene, backend="golden").radiosity
    model = render(scene, backend="model").radiosity
    per_channel = np.sqrt(((model - golden) ** 2).mean(axis=0) / (golden ** 2).mean(axis=0))
    rms = np.sqrt(((model - golden) ** 2).mean() / (golden ** 2).mean())
    print(f"{scene.name}: model vs golden RMS relative {rms:.3e}, per channel {per_channel}")
    assert rms < 1e-4
    assert per_channel.max() < 1e-4

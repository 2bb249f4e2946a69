"""blockray sweep: the grid, the error against a reference on its mesh, the front, and the command.

The errors a sweep reports are checked against the same numbers computed here from the points'
and the reference's ``--patches`` CSVs with plain numpy, not with the sweep's code."""

import csv
import json
import os
import shlex

import numpy as np
import pytest

from blockray.host_driver.cli import build_parser
from blockray.host_driver.render.sweep import map_to_mesh, pareto_front, parse_vary, points
from clirun import cli
from scenes import room_obj


@pytest.fixture
def room(tmp_path):
    """A closed 2 m room, one emitting wall, a block that casts shadows (tests/scenes.py)."""
    return str(room_obj(tmp_path))


def run(capsys, *argv):
    return cli(capsys, argv)


@pytest.mark.parametrize("vary, needle", [
    (["bits"], "expected NAME=V1,V2"),
    (["speed=1,2"], "not a setting a sweep can vary"),
    (["bits=12,x"], "'x' is not an integer"),
    (["bits=2,14"], "must be from"),
    (["samples=0"], "must be positive"),
    (["epsilon=0"], "must be positive"),
    (["solver=newton"], "not one of progressive"),
    (["board=ulx3s"], "not one of"),
    (["bits=12", "bits=14"], "given twice"),
    (["tolerance=1e-3,0.001"], "repeated"),
])
def test_a_bad_vary_is_one_line_and_exit_2(capsys, tmp_path, vary, needle):
    code, err = run(capsys, "sweep", "cornell", *(a for v in vary for a in ("--vary", v)), "--out", str(tmp_path))
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("blockray: error: --vary") and needle in err, err
    assert not os.path.exists(tmp_path / "sweep.csv")


def test_the_grid_is_every_combination_in_order():
    grid = parse_vary(["bits=12,14", "samples=4,8,16", "tolerance=1e-2"])
    got = [(p["bits"], p["samples"], p["tolerance"]) for p in points(grid)]
    assert got == [(b, s, 1e-2) for b in (12, 14) for s in (4, 8, 16)]


def test_pareto_front_is_the_undominated_points():
    seed = 29
    rng = np.random.default_rng(seed)
    print(f"seed {seed}")
    for _ in range(200):
        pts = list(zip(rng.integers(0, 6, 12).tolist(), rng.integers(0, 6, 12).tolist()))
        front = pareto_front([c for c, _ in pts], [e for _, e in pts])
        undominated = {p for p in pts if not any(q[0] <= p[0] and q[1] <= p[1] and q != p for q in pts)}
        assert [pts[i] for i in front] == sorted(undominated)      # one point for each, by cost


def tessellated_cube(rng, n):
    """The surface of a cube, each face an n x n grid of jittered points cut into triangles: (T, 3, 3), groups."""
    tris, groups = [], []
    for face in range(6):
        axis, side = face // 2, face % 2
        u, w = [a for a in range(3) if a != axis]
        grid = np.stack(np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij"), axis=-1)
        grid[1:-1, 1:-1] += rng.uniform(-0.3, 0.3, (n - 1, n - 1, 2)) / n
        pts = np.zeros((n + 1, n + 1, 3))
        pts[..., axis], pts[..., u], pts[..., w] = side, grid[..., 0], grid[..., 1]
        for i in range(n):
            for j in range(n):
                a, b, c, d = pts[i, j], pts[i + 1, j], pts[i + 1, j + 1], pts[i, j + 1]
                tris += [(a, b, c), (a, c, d)]
                groups += [face, face]
    return np.array(tris), np.array(groups).astype(str)


def test_centroids_of_a_finer_mesh_land_in_their_parent_triangles():
    """Each 4-way midpoint child's centroid maps to its parent, on rotated, scaled, rounded meshes."""
    seed = 2029
    rng = np.random.default_rng(seed)
    print(f"seed {seed}")
    for _ in range(5):
        parents, groups = tessellated_cube(rng, int(rng.integers(2, 9)))
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        parents = np.round(parents @ q * 10 ** rng.uniform(-2, 3), 6)
        a, b, c = parents[:, 0], parents[:, 1], parents[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        children = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
        parent_of = np.tile(np.arange(len(parents)), 4)
        assert (map_to_mesh(children.mean(axis=1), groups[parent_of], parents, groups) == parent_of).all()
        # the same mesh maps to itself
        assert (map_to_mesh(parents.mean(axis=1), groups, parents, groups) == np.arange(len(parents))).all()


def read(path):
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    area = np.array([float(r["area"]) for r in rows])
    b = np.array([[float(r[k]) for k in ("B_r", "B_g", "B_b")] for r in rows])
    return area, b


def test_sweep_writes_points_tables_and_plot_and_resumes(capsys, tmp_path, room):
    out = tmp_path / "sw"
    args = ["sweep", room, "--vary", "samples=2,4", "--vary", "bits=10,12", "--fix", "max-edge=1.0",
            "--fix", "voxels=3", "--reference", "golden", "--out", str(out)]
    code, err = run(capsys, *args)
    assert code == 0, err
    with open(out / "sweep.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["samples"] for r in rows] == ["2", "2", "4", "4"] and [r["bits"] for r in rows] == ["10", "12"] * 2
    for col in ("error_rms", "error_max", "cpu_s", "wall_s", "rays", "tests", "board_cycles", "board_s", "command"):
        assert col in rows[0]
    ref_area, ref = read(out / "reference" / "patches.csv")
    for r in rows:
        assert r["status"] == "ok"
        _, b = read(out / "points" / f"samples-{r['samples']}_bits-{r['bits']}" / "patches.csv")
        rms = np.sqrt((ref_area[:, None] * (b - ref) ** 2).sum(0) / (ref_area[:, None] * ref ** 2).sum(0))
        assert float(r["error_rms"]) == pytest.approx(rms.max(), rel=1e-12)
        assert float(r["error_rms_g"]) == pytest.approx(rms[1], rel=1e-12)
        assert 0 < rms.max() < 0.2
        assert float(r["board_s"]) == pytest.approx(int(r["board_cycles"]) / 50e6)
    assert (out / "pareto.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    meta = json.loads((out / "sweep.json").read_text())
    assert meta["reference"]["recipe"]["board"] == "golden" and len(meta["points"]) == 4
    # the command printed on the plot and kept in the JSON sweeps the same grid again
    again = build_parser().parse_args(shlex.split(meta["command"])[1:] + ["--out", str(out)])
    given = build_parser().parse_args(args)
    assert again.scene == given.scene and again.reference == given.reference
    assert parse_vary(again.vary) == parse_vary(given.vary) and parse_vary(again.fix, "--fix") == parse_vary(given.fix, "--fix")

    stamp = {p: os.stat(out / "points" / p / "report.json").st_mtime_ns for p in os.listdir(out / "points")}
    code, err = run(capsys, *args)
    assert code == 0, err and "rendered" not in err          # nothing rendered again
    assert stamp == {p: os.stat(out / "points" / p / "report.json").st_mtime_ns for p in os.listdir(out / "points")}
    with open(out / "sweep.csv", newline="") as f:
        again = list(csv.DictReader(f))
    assert [r["error_rms"] for r in again] == [r["error_rms"] for r in rows]


def test_a_failing_point_is_reported_and_the_sweep_exits_2(capsys, tmp_path, room):
    out = tmp_path / "sw"
    # 4 bits cannot hold this scene's sample points: the render itself refuses that point
    code, err = run(capsys, "sweep", room, "--vary", "bits=4,12", "--fix", "max-edge=1.0", "--fix", "voxels=3",
                    "--reference", "golden", "--out", str(out), "--quiet")
    assert code == 2 and err.count("\n") == 1 and "1 of 2 points failed" in err, err
    with open(out / "sweep.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows[0]["status"].startswith("failed") and rows[0]["error_rms"] == ""
    assert rows[1]["status"] == "ok"


def test_a_hierarchical_point_is_measured_on_its_leaves(capsys, tmp_path, room):
    """A hierarchical point's CSV has its own leaves; the reference patch i's value must be the leaf
    that holds its centroid. Here the reference mesh is the input triangles, and the leaf holding an
    input triangle's centroid is the one at the end of the middle children, with that same centroid."""
    out = tmp_path / "sw"
    code, err = run(capsys, "sweep", room, "--vary", "solver=hierarchical", "--vary", "epsilon=1e-3",
                    "--fix", "max-edge=1.0", "--fix", "voxels=3", "--reference", "golden", "--out", str(out),
                    "--quiet")
    assert code == 0, err
    with open(out / "sweep.csv", newline="") as f:
        row, = list(csv.DictReader(f))
    ref_area, ref = read(out / "reference" / "patches.csv")
    with open(out / "points" / "solver-hierarchical_epsilon-0.001" / "patches.csv", newline="") as f:
        leaves = list(csv.DictReader(f))
    assert int(row["patches"]) == len(leaves) > len(ref_area)          # it refined
    with open(out / "reference" / "patches.csv", newline="") as f:
        centre = np.array([[float(r[k]) for k in ("cx", "cy", "cz")] for r in csv.DictReader(f)])
    b = np.empty_like(ref)
    for i in range(len(ref)):
        mine = [r for r in leaves if int(r["patch"]) == i]
        d = [np.abs(np.array([float(r[k]) for k in ("cx", "cy", "cz")]) - centre[i]).max() for r in mine]
        assert min(d) < 1e-9
        b[i] = [float(mine[int(np.argmin(d))][k]) for k in ("B_r", "B_g", "B_b")]
    rms = np.sqrt((ref_area[:, None] * (b - ref) ** 2).sum(0) / (ref_area[:, None] * ref ** 2).sum(0))
    assert float(row["error_rms"]) == pytest.approx(rms.max(), rel=1e-12)

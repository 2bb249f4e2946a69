"""Form-factor accuracy against oracles, and the energy balance of closed scenes.

    python benchmarks/bench_formfactor.py table      # each method's error vs the mpmath contour oracle
    python benchmarks/bench_formfactor.py energy     # closed scenes: absorbed vs emitted power
    python benchmarks/bench_formfactor.py rows       # visible row sums per shooter vs sample count
    python benchmarks/bench_formfactor.py ends       # visible row sums with end points on the receiver too
    python benchmarks/bench_formfactor.py change OLD.csv NEW.csv   # radiosity change per channel
    python benchmarks/bench_formfactor.py boards     # golden board's exact predicate vs the model's kernel
    python benchmarks/bench_formfactor.py closure    # closed scenes: reciprocity / summation errors,
                                                     # raw and enforced energy balance side by side

``table``: random triangle pairs of each kind (each wholly in front of the other, so the oracles'
unclipped integrands apply), every method of host_driver/formfactor.py forced on each pair, and
pyviewfactor's SA-30 kernel, against the double contour integral with the inner integral in closed
form and the outer one by mpmath's adaptive quadrature at 30 digits. Prints a markdown table of
the largest relative error per method and kind. Numbers go into docs/formfactors.md.

``energy``: closed scenes rendered with the golden board; absorbed power sum (1 - rho) H A with
H = (B - E) / rho, against emitted power sum E A, per channel.
"""

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from _run_header import print_run_header                                   # noqa: E402
from blockray.host_driver import formfactor as ff                            # noqa: E402
from blockray.host_driver.closure import absorbed_balance                    # noqa: E402
from blockray.host_driver.render import render                               # noqa: E402

KINDS = {  # name: (generator kind for test_formfactor.random_pair, distance for "far" pairs)
    "shared edge": ("edge", None), "shared vertex": ("vertex", None), "near (0.05 apart)": ("near", None),
    "general (~2 apart)": ("general", None), "D/L ~ 5": ("far", 5), "D/L ~ 20": ("far", 20),
    "D/L ~ 60": ("far", 60), "D/L ~ 200": ("far", 200),
}


def far_pair(rng, D):
    """Two triangles of size ~1 whose centroids are D apart, facing each other, no clipping."""
    while True:
        Ti = rng.normal(size=(3, 3)) * 0.4
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        Tj = rng.normal(size=(3, 3)) * 0.4 + D * d
        if np.cross(Ti[1] - Ti[0], Ti[2] - Ti[0]) @ d < 0:
            Ti = Ti[::-1]
        if np.cross(Tj[1] - Tj[0], Tj[2] - Tj[0]) @ d > 0:
            Tj = Tj[::-1]
        ni, nj = np.cross(Ti[1] - Ti[0], Ti[2] - Ti[0]), np.cross(Tj[1] - Tj[0], Tj[2] - Tj[0])
        if ((Tj - Ti[0]) @ ni >= 0).all() and ((Ti - Tj[0]) @ nj >= 0).all():
            return Ti, Tj


def forced(Ti, Tj):
    """A_j F_ji by every method: closed form, centroid, 7-point, 64-point cubature."""
    nj = np.cross(Tj[1] - Tj[0], Tj[2] - Tj[0])
    Aj = 0.5 * np.linalg.norm(nj)
    nj = nj / (2 * Aj)
    poly = np.empty((4, 3))
    c = Tj.mean(axis=0)
    out = {"closed form": ff.pair_factors(Ti[None], Tj[None], target=0.0)[0],
           "centroid": Aj * ff._lambert(c[0], c[1], c[2], nj[0], nj[1], nj[2], Ti, poly),
           "7-point": Aj * ff._cubature(Ti, Tj, nj[0], nj[1], nj[2], ff._RULE7, ff._RULE7_W, poly),
           "64-point": Aj * ff._cubature(Ti, Tj, nj[0], nj[1], nj[2], ff._RULE64, ff._RULE64_W, poly)}
    stats = np.zeros(len(ff.METHODS), dtype=np.int64)
    out["default"] = ff.pair_factors(Ti[None], Tj[None], stats=stats)[0]
    return out, ff.METHODS[int(np.argmax(stats))]


def table(args):
    from test_formfactor import contour_oracle, random_pair
    from pyviewfactor.pvf_integrators import compute_viewfactor_sa30
    rng = np.random.default_rng(args.seed)
    print(f"seed={args.seed}, {args.pairs} pairs per kind")
    methods = ["closed form", "centroid", "7-point", "64-point", "default", "pyviewfactor SA-30"]
    print("| pairs | " + " | ".join(methods) + " | default picks |")
    print("|---|" + "---|" * (len(methods) + 1))
    for name, (kind, D) in KINDS.items():
        worst = dict.fromkeys(methods, 0.0)
        picks = {}
        for _ in range(args.pairs):
            Ti, Tj = far_pair(rng, D) if D else random_pair(rng, kind)
            oracle = contour_oracle(Tj, Ti, dps=30)
            got, pick = forced(Ti, Tj)
            Ai = 0.5 * np.linalg.norm(np.cross(Ti[1] - Ti[0], Ti[2] - Ti[0]))
            got["pyviewfactor SA-30"] = Ai * compute_viewfactor_sa30(np.ascontiguousarray(Tj),
                                                                     np.ascontiguousarray(Ti), 4 * np.pi * Ai)
            for m in methods:
                worst[m] = max(worst[m], abs(got[m] / oracle - 1))
            picks[pick] = picks.get(pick, 0) + 1
        print(f"| {name} | " + " | ".join(f"{worst[m]:.1e}" for m in methods) + " | "
              + ", ".join(f"{k} {v}" for k, v in picks.items()) + " |", flush=True)




def icosphere(levels, centre, radius):
    """Outward-facing icosphere of 20 * 4^levels triangles."""
    import itertools
    phi = (1 + 5 ** 0.5) / 2
    pts = np.array([p for s1 in (-1, 1) for s2 in (-1, 1)
                    for p in ((0, s1, s2 * phi), (s1, s2 * phi, 0), (s2 * phi, 0, s1))], float)
    faces = [f for f in itertools.combinations(range(12), 3)
             if all(abs(np.linalg.norm(pts[i] - pts[j]) - 2) < 1e-9 for i, j in itertools.combinations(f, 2))]
    tris = pts[np.array(faces)]
    for _ in range(levels):
        a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        tris = np.concatenate([np.stack(x, 1) for x in ([a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca])])
    tris = tris / np.linalg.norm(tris, axis=2, keepdims=True)
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    flip = (n * tris.mean(axis=1)).sum(axis=1) < 0
    tris[flip] = tris[flip][:, ::-1]
    return tris * radius + centre


def closed_scenes():
    from test_formfactor import closed_box, make_scene
    from blockray.host_driver.builtin import load_scene
    rho = [0.5, 0.3, 0.7]
    box, face = closed_box(4)
    E = np.zeros((len(box), 3))
    E[0] = [1, 2, 0.5]
    yield "empty closed box (192 triangles, one emitting corner triangle)", make_scene(box, reflectance=rho, emission=E)
    sphere = icosphere(2, np.array([0.5, 0.45, 0.5]), 0.25)
    tris = np.concatenate([box, sphere])
    E = np.zeros((len(tris), 3))
    E[:len(box)][face == 1] = [1, 2, 0.5]
    R = np.full((len(tris), 3), rho)
    R[len(box):] = [0.8, 0.6, 0.2]
    yield (f"icosphere of {len(sphere)} triangles in a closed box ({len(tris)} triangles, lit ceiling)",
           make_scene(tris, reflectance=R, emission=E))
    yield "cornell closed by a front wall", closed_cornell(load_scene("cornell"))


def closed_cornell(scene):
    """cornell with its open side (the one facing the camera) closed by the bounding box's face,
    subdivided; the face covers the opening (cornell's red wall is slanted, so it reaches past it
    outside the box, where no light arrives)."""
    from test_formfactor import rectangle
    from blockray.host_driver.scene import Scene
    lo, hi = scene.bbox
    cam = np.asarray(scene.camera.position, dtype=float)
    outside = np.maximum(lo - cam, cam - hi)              # how far the camera is beyond each face
    axis = int(np.argmax(outside))
    value = lo[axis] if cam[axis] < lo[axis] else hi[axis]
    u, v = [a for a in range(3) if a != axis]
    origin = lo.copy()
    origin[axis] = value
    du, dv = np.zeros(3), np.zeros(3)
    du[u], dv[v] = hi[u] - lo[u], hi[v] - lo[v]
    n = max(1, round(math.sqrt(scene.patches / 10)))
    wall = rectangle(origin, du, dv, n, n)
    inward = np.sign(scene.centroids.mean(axis=0)[axis] - value)
    normal = np.cross(wall[0, 1] - wall[0, 0], wall[0, 2] - wall[0, 0])
    if normal[axis] * inward < 0:
        wall = wall[:, ::-1]
    k = len(scene.vertices)
    vertices = np.concatenate([scene.vertices, wall.reshape(-1, 3)])
    triangles = np.concatenate([scene.triangles, k + np.arange(3 * len(wall)).reshape(-1, 3)])
    m = len(wall)
    return Scene(name=scene.name + "-closed", vertices=vertices, triangles=triangles,
                 reflectance=np.concatenate([scene.reflectance, np.full((m, 3), 0.6)]),
                 emission=np.concatenate([scene.emission, np.zeros((m, 3))]),
                 group=np.concatenate([scene.group, np.full(m, len(scene.group_names))]),
                 group_names=scene.group_names + ["front wall"], camera=scene.camera, source=scene.source)


def energy(args):
    print("| scene | board | patches | residual | absorbed / emitted - 1 (R, G, B) | seconds |")
    print("|---|---|---|---|---|---|")
    for name, scene in closed_scenes():
        if args.only and args.only not in name:
            continue
        for board in args.boards.split(","):
            t = time.perf_counter()
            res = render(scene, board=board, tolerance=args.tolerance)
            bal = absorbed_balance(scene, res.radiosity)
            print(f"| {name} | {board} | {scene.patches} | {res.report['residual']:.1e} | "
                  + ", ".join(f"{x:+.1e}" for x in bal) + f" | {time.perf_counter() - t:.0f} |", flush=True)


def closure(args):
    """Each closed scene rendered once with ``closure=args.mode``: the raw visible factors'
    summation and reciprocity errors (host_driver/closure.py), the size of the correction, and the
    energy balance solved with the raw and the corrected factors."""
    import json
    for name, scene in closed_scenes():
        if args.only and args.only not in name:
            continue
        t = time.perf_counter()
        res = render(scene, board=args.board, tolerance=args.tolerance, solver=args.solver, closure=args.mode)
        c = res.report["closure"]
        print(json.dumps({"scene": name, "patches": scene.patches, "board": args.board, "solver": args.solver,
                          "residual": res.report["residual"], "seconds": round(time.perf_counter() - t, 1),
                          **c}), flush=True)


def boards(args):
    """Golden board (exact predicate) against the model board's compiled kernel on the same
    shooters' rays: rays and tests per CPU second of each board's ``run``, one thread,
    alternating rounds (a shared machine's load hits both alike), the ratio per round. The boards
    count tests differently (golden: rays x patches of the block's voxels; model: the hardware's
    tests, records streamed x R x S), so rays/s is the like-for-like figure. Each board's first
    shooter compiles its kernels and is not timed."""
    from blockray.host_driver.builtin import load_scene
    from blockray.host_driver.render import make_board, Visibility
    from blockray.host_driver.voxel import VoxelGrid, default_voxels
    from blockray.params import BoardParams
    from blockray.samples import SampleScheme
    from blockray import threads
    scene = load_scene(args.scene)
    samples, p = SampleScheme(8), BoardParams()
    rng = np.random.default_rng(args.seed)
    shooters = rng.choice(scene.patches, args.shooters + 1, replace=False)
    print(f"scene {scene.name}, {args.shooters} shooters (seed {args.seed}), {args.rounds} rounds, 1 thread")
    with threads.using(1):
        setups = {}
        for name in ("golden", "model"):
            board = make_board(name, p)
            board.prepare(scene, samples)
            grid = VoxelGrid(scene.patch_vertices, default_voxels(scene.patches, parallelism=1), margin=board.margin)
            board.load(grid)
            vis = Visibility(scene, board, grid, samples, rows=p.rows, cols=p.cols)
            i = shooters[0]
            vis.clear_fraction(i, np.flatnonzero(ff.exchange_mask(scene, i)))          # compile
            setups[name] = (board, vis)
        for r in range(args.rounds):
            rate = {}
            for name, (board, vis) in setups.items():
                tests0, rays0, cpu0 = board.counters()["tests"], vis.rays, vis.phases.cpu.get("board", 0.0)
                for i in shooters[1:]:
                    vis.clear_fraction(i, np.flatnonzero(ff.exchange_mask(scene, i)))
                tests, rays = board.counters()["tests"] - tests0, vis.rays - rays0
                cpu = vis.phases.cpu["board"] - cpu0
                rate[name] = (tests / cpu, rays / cpu)
                print(f"round {r}: {name}: {rays} rays, {tests} tests, {cpu:.3f} s CPU: {rays / cpu / 1e6:.2f} M rays/s, "
                      f"{tests / cpu / 1e6:.1f} M tests/s", flush=True)
            print(f"round {r}: golden / model: rays/s {rate['golden'][1] / rate['model'][1]:.3f}, "
                  f"tests/s {rate['golden'][0] / rate['model'][0]:.3f}", flush=True)


def _radiosity(path):
    """(N, 3) radiosity of a ``--patches`` CSV (``blockray render ... --patches``) or a .npy."""
    if path.endswith(".npy"):
        return np.load(path)
    return np.loadtxt(path, delimiter=",", skiprows=1, usecols=(6, 7, 8), ndmin=2)


def change_stats(B, ref):
    """RMS relative change of B against ref (all channels, and per channel), and per channel the
    largest and 99th-percentile per-patch relative change over the patches lit in ref, the change
    of the channel's total, and the patches dark in ref (lit in B)."""
    def rms(x, y):
        return float(np.sqrt(np.mean((x - y) ** 2)) / np.sqrt(np.mean(y ** 2)))
    out = {"rms": rms(B, ref)}
    for c, ch in enumerate("RGB"):
        lit = ref[:, c] > 0
        rel = np.abs(B[lit, c] - ref[lit, c]) / ref[lit, c]
        out[ch] = {"rms": rms(B[:, c], ref[:, c]), "max": float(rel.max()), "p99": float(np.quantile(rel, 0.99)),
                   "total": float(B[:, c].sum() / ref[:, c].sum() - 1),
                   "dark_in_ref": int((~lit).sum()), "dark_in_ref_lit_now": int((~lit & (B[:, c] > 0)).sum())}
    return out


def change(args):
    """Radiosity change between two renders of one scene (e.g. before and after a change, or the
    model against golden), from their ``--patches`` CSVs."""
    import json
    print(json.dumps({"ref": args.ref, "new": args.new, **change_stats(_radiosity(args.new), _radiosity(args.ref))}))


def end_points(args):
    """Row sums of the icosphere scene's box shooters (every 6th triangle) with visibility from K
    shooter samples to 1 (the centroid) or K (the same sample scheme) end points on each receiver,
    exact predicate over every patch, uniform weights over the samples in front of the other
    patch's plane: does sampling the receiver too remove the deficit?"""
    from blockray.exact_float import blocked_rays
    from blockray.samples import SampleScheme
    scene = next(s for name, s in closed_scenes() if name.startswith("icosphere"))
    K = args.samples
    samples = SampleScheme(K)
    W = np.asarray(samples.weights, dtype=np.int64)
    V, A = scene.patch_vertices, scene.areas
    res = {1: [], K: []}
    for i in range(0, 192, 6):
        f = ff.unoccluded_factors(scene, i)
        rec = np.flatnonzero(f > 0)
        front_i = ff.samples_in_front(scene, samples, i, rec).astype(float)     # (R, K)
        vis = {1: np.zeros(len(rec)), K: np.zeros(len(rec))}
        for r, j in enumerate(rec):
            front_j = ff.samples_in_front(scene, samples, j, [i])[0].astype(float)
            for M, Q_w, mask in ((1, np.ones((1, 3), dtype=np.int64), np.ones(1)), (K, W, front_j)):
                clear = ~blocked_rays(np.repeat(V[i][None], K, axis=0), W, np.repeat(V[j][None], M, axis=0), Q_w, V)
                w = mask[:, None] * front_i[r][None, :]
                vis[M][r] = (clear * w).sum() / w.sum() if w.sum() > 0 else clear.mean()
        for M in (1, K):
            res[M].append((A[rec] * f[rec] * vis[M]).sum() / A[i] - 1)
    for M in (1, K):
        x = np.array(res[M])
        print(f"K = {K} shooter samples, {M} end point(s) per receiver: {len(x)} box shooters, row sum - 1: "
              f"mean {x.mean():+.2e}, min {x.min():+.2e}, max {x.max():+.2e}", flush=True)


def row_sums(args):
    """Visible row sums sum_j F_ij v_ij / 1 - 1 of the box's shooters in the icosphere scene, with
    the render's visibility (render.shoot's rule) at a given shooter sample count."""
    from blockray.host_driver.render import make_board, Visibility
    from blockray.host_driver.voxel import VoxelGrid, default_voxels
    from blockray.params import BoardParams
    from blockray.samples import SampleScheme
    scene = next(s for name, s in closed_scenes() if name.startswith("icosphere"))
    A = scene.areas
    for K in args.samples:
        samples = SampleScheme(K)
        board = make_board("golden")
        board.prepare(scene, samples)
        grid = VoxelGrid(scene.patch_vertices, default_voxels(scene.patches, parallelism=1), margin=board.margin)
        board.load(grid)
        p = BoardParams()
        vis = Visibility(scene, board, grid, samples, rows=p.rows, cols=p.cols)
        rows = []
        for i in range(0, 192, 6):                          # every 6th triangle of the box
            f = ff.unoccluded_factors(scene, i)
            rec = np.flatnonzero(f > 0)
            direct = ff.centroid_in_front(scene, i, rec)
            v = np.empty(len(rec))
            weigh = ff.sample_weights if args.kernel else (
                lambda sc, sa, a, b: ff.samples_in_front(sc, sa, a, b).astype(float))
            v[direct] = vis.clear_fraction(i, rec[direct], weigh(scene, samples, i, rec[direct]))
            for m in np.flatnonzero(~direct):
                j = rec[m]
                v[m] = vis.clear_fraction(j, np.array([i]), weigh(scene, samples, j, [i]))[0]
            rows.append((A[rec] * f[rec] * v).sum() / A[i] - 1)
        rows = np.array(rows)
        print(f"K = {K}, {'kernel-weighted' if args.kernel else 'uniform'} rays: {len(rows)} box shooters, row sum - 1: mean {rows.mean():+.2e}, "
              f"min {rows.min():+.2e}, max {rows.max():+.2e}", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    t = sub.add_parser("table")
    t.add_argument("--pairs", type=int, default=8)
    t.add_argument("--seed", type=int, default=17)
    e = sub.add_parser("energy")
    e.add_argument("--boards", default="golden")
    e.add_argument("--tolerance", type=float, default=1e-6)
    e.add_argument("--only", default=None, help="only scenes whose name contains this")
    c = sub.add_parser("closure")
    c.add_argument("--board", default="golden")
    c.add_argument("--mode", default="enforce", help="render's closure mode: symmetric or enforce")
    c.add_argument("--solver", default="progressive")
    c.add_argument("--tolerance", type=float, default=1e-6)
    c.add_argument("--only", default=None, help="only scenes whose name contains this")
    b = sub.add_parser("boards")
    b.add_argument("--scene", default="cornell")
    b.add_argument("--shooters", type=int, default=20)
    b.add_argument("--rounds", type=int, default=3)
    b.add_argument("--seed", type=int, default=17)
    ch = sub.add_parser("change")
    ch.add_argument("ref", help="reference radiosity: --patches CSV or .npy")
    ch.add_argument("new", help="radiosity compared with it")
    en = sub.add_parser("ends")
    en.add_argument("--samples", type=int, default=8)
    r = sub.add_parser("rows")
    r.add_argument("--samples", type=int, nargs="+", default=[8, 32])
    r.add_argument("--kernel", action="store_true", help="weigh rays by formfactor.sample_weights")
    args = ap.parse_args(argv)
    print_run_header()
    {"table": table, "energy": energy, "rows": row_sums, "closure": closure, "boards": boards, "change": change, "ends": end_points}[args.what](args)


if __name__ == "__main__":
    main()

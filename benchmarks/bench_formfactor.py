"""Form-factor accuracy against oracles, and the energy balance of closed scenes.

    python benchmarks/bench_formfactor.py table      # each method's error vs the mpmath contour oracle
    python benchmarks/bench_formfactor.py energy     # closed scenes: absorbed vs emitted power
    python benchmarks/bench_formfactor.py rows       # visible row sums per shooter vs sample count
    python benchmarks/bench_formfactor.py speed cornell room   # CPU us per pair, against pyviewfactor
    python benchmarks/bench_formfactor.py grazing    # cornell's grazing pairs: closed form and default vs mpmath
    python benchmarks/bench_formfactor.py trigger    # the closed form's error against its cancellation estimate
    python benchmarks/bench_formfactor.py versus cornell room   # against an earlier formfactor.py: speed, radiosity
    python benchmarks/bench_formfactor.py unresolved cornell room   # pairs no route certifies
    python benchmarks/bench_formfactor.py ends       # visible row sums with end points on the receiver too
    python benchmarks/bench_formfactor.py estimators # energy balance of an occluded box per visibility estimator
    python benchmarks/bench_formfactor.py rules      # the same through the render, per --end-points rule
    python benchmarks/bench_formfactor.py shooters room   # the shooters that unbalance a render, against Embree
    python benchmarks/bench_formfactor.py change OLD.csv NEW.csv   # radiosity change per channel
    python benchmarks/bench_formfactor.py boards     # golden board's exact predicate vs the model's kernel
    python benchmarks/bench_formfactor.py closure    # closed scenes: reciprocity / summation errors,
                                                     # raw and enforced energy balance side by side

``versus`` needs the earlier module beside the new one (not committed), e.g.
``git show 10cb08c:host_driver/formfactor.py > host_driver/_formfactor_before.py``.

``table``: random triangle pairs of each kind (each wholly in front of the other, so the oracles'
unclipped integrands apply), every method of host_driver/radiosity/formfactor.py forced on each pair, and
pyviewfactor's SA-30 kernel, against the double contour integral with the inner integral in closed
form and the outer one by mpmath's adaptive quadrature at 30 digits. Prints a markdown table of
the largest relative error per method and kind. Numbers go into docs/formfactors.md.

``speed``: the pairs a render computes (every ``--step``-th shooter's exchange mask), on one
thread: CPU microseconds per pair of the closed form alone (``target=0``, the reference) and of
the default (far pairs by cubature), the pairs per method, and pyviewfactor's SA-30 kernel on the
first ``--peer-pairs`` of them (the peer); and the share of the pairs a render computes once
(each unordered pair, :class:`~blockray.host_driver.radiosity.formfactor.PairCache`).

``grazing``: a seeded sample of cornell's grazing pairs (a centroid cosine below ``--cosine``,
centroids over ``--distance`` apart; pairs coplanar to rounding, cosines below 1e-12, left out),
unclipped and clipped, each against the mpmath oracle of the clipped polygons: the closed form
alone (``target=0``; what the default gave these pairs before issue 17's grazing-pair cubature)
and the default.

``energy``: closed scenes rendered with the golden board; absorbed power sum (1 - rho) H A with
H = (B - E) / rho, against emitted power sum E A, per channel.
"""

import argparse
import time

import numpy as np

import _shared  # noqa: F401  (tests/ on the path: the tests' scenes and oracles)
from _run_header import print_run_header
from blockray.host_driver.radiosity import closed_form, cubature, formfactor as ff, point_factor, ray_weights
from blockray.host_driver.radiosity.closure import absorbed_balance
from blockray.host_driver.radiosity.elements import level_corners
from blockray.host_driver.render.render import render

from oracles import clip_front, contour_oracle, far_pair, random_pair
from scenes import box_with_block, closed_box_with_slab, closed_scenes

KINDS = {  # name: (generator kind for oracles.random_pair, distance for oracles.far_pair)
    "shared edge": ("edge", None), "shared vertex": ("vertex", None), "near (0.05 apart)": ("near", None),
    "general (~2 apart)": ("general", None), "D/L ~ 5": ("far", 5), "D/L ~ 20": ("far", 20),
    "D/L ~ 60": ("far", 60), "D/L ~ 200": ("far", 200),
}


def forced(Ti, Tj):
    """A_j F_ji by every method: closed form, centroid, 7-, 25- and 64-point cubature."""
    nj = np.cross(Tj[1] - Tj[0], Tj[2] - Tj[0])
    Aj = 0.5 * np.linalg.norm(nj)
    nj = nj / (2 * Aj)
    poly = np.empty((4, 3))
    c = Tj.mean(axis=0)
    out = {"closed form": ff.pair_factors(Ti[None], Tj[None], target=0.0)[0],
           "centroid": Aj * point_factor._lambert(c[0], c[1], c[2], nj[0], nj[1], nj[2], Ti, poly),
           "7-point": Aj * cubature._cubature(Ti, Tj, nj[0], nj[1], nj[2], cubature._RULE7, cubature._RULE7_W, poly),
           "25-point": Aj * cubature._cubature(Ti, Tj, nj[0], nj[1], nj[2], cubature._RULE25, cubature._RULE25_W, poly),
           "64-point": Aj * cubature._cubature(Ti, Tj, nj[0], nj[1], nj[2], cubature._RULE64, cubature._RULE64_W, poly)}
    stats = np.zeros(len(ff.METHODS), dtype=np.int64)
    out["default"] = ff.pair_factors(Ti[None], Tj[None], stats=stats)[0]
    return out, ff.METHODS[int(np.argmax(stats))]


def table(args):
    from pyviewfactor.pvf_integrators import compute_viewfactor_sa30
    rng = np.random.default_rng(args.seed)
    print(f"seed={args.seed}, {args.pairs} pairs per kind")
    methods = ["closed form", "centroid", "7-point", "25-point", "64-point", "default", "pyviewfactor SA-30"]
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




def energy(args):
    print("| scene | board | patches | residual | absorbed / emitted - 1 (R, G, B) | seconds |")
    print("|---|---|---|---|---|---|")
    for name, scene in closed_scenes():
        if args.only and args.only not in name:
            continue
        for board in args.boards.split(","):
            t = time.perf_counter()
            res = render(scene, backend=board, tolerance=args.tolerance)
            bal = absorbed_balance(scene, res.radiosity)
            print(f"| {name} | {board} | {scene.patches} | {res.report['residual']:.1e} | "
                  + ", ".join(f"{x:+.1e}" for x in bal) + f" | {time.perf_counter() - t:.0f} |", flush=True)


def closure(args):
    """Each closed scene rendered once with ``closure=args.mode``: the raw visible factors'
    summation and reciprocity errors (host_driver/radiosity/closure.py), the size of the correction, and the
    energy balance solved with the raw and the corrected factors."""
    import json
    for name, scene in closed_scenes():
        if args.only and args.only not in name:
            continue
        t = time.perf_counter()
        res = render(scene, backend=args.board, tolerance=args.tolerance, solver=args.solver, closure=args.mode)
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
    from blockray.host_driver.scene.builtin import load_scene
    from blockray.host_driver.render.render import make_board, Visibility
    from blockray.host_driver.traverse.voxel import VoxelGrid
    from blockray.host_driver.traverse.cost import default_voxels
    from blockray.params import BoardParams
    from blockray.samples import SampleScheme
    from blockray import threads
    scene = load_scene(args.scene)
    samples, p = SampleScheme(8), BoardParams(bits=None)
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
    ref, new = _radiosity(args.ref), _radiosity(args.new)
    print(json.dumps({"ref": args.ref, "new": args.new, **change_stats(new, ref)}))
    if args.worst:
        groups = (np.loadtxt(args.ref, delimiter=",", skiprows=1, usecols=1, dtype=str, ndmin=1)
                  if not args.ref.endswith(".npy") else np.full(len(ref), "patch"))
        rel = np.abs(new - ref).max(axis=1) / np.maximum(ref.max(axis=1), 1e-300)
        median = np.median(ref, axis=0)
        print(f"patches with the largest relative change (radiosity median {median.round(3).tolist()}):")
        for i in np.argsort(-rel)[:args.worst]:
            print(f"  {i} {groups[i]}: {ref[i].round(6).tolist()} -> {new[i].round(6).tolist()} ({rel[i]:.1%})")


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
        front_i = ray_weights.samples_in_front(scene, samples, i, rec).astype(float)     # (R, K)
        vis = {1: np.zeros(len(rec)), K: np.zeros(len(rec))}
        for r, j in enumerate(rec):
            front_j = ray_weights.samples_in_front(scene, samples, j, [i])[0].astype(float)
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


def _sub_centroids(T, levels):
    """Centroids of the 4^levels congruent sub-triangles of each triangle: (N, 4^levels, 3)."""
    return _sub_triangles(T, levels).mean(axis=2)


def _kernel(p, n_p, q, n_q):
    """Point-to-point kernel cos cos / r^2 (up to 1/pi), each cosine clipped at 0 (broadcasts)."""
    d = q - p
    r2 = (d * d).sum(-1)
    return np.maximum((d * n_p).sum(-1), 0) * np.maximum(-(d * n_q).sum(-1), 0) / np.maximum(r2, 1e-300) ** 2


def _sub_triangles(T, levels):
    """The 4^levels congruent sub-triangles of each triangle, in the element table's order (the first
    cut outermost): (N, 4^levels, 3, 3)."""
    return np.einsum("cvk,nkd->ncvd", level_corners(levels), T)


def _cdf(g):
    """(M, C) cumulative distribution of each row's density g[m] (uniform where g[m] vanishes)."""
    p = np.where(g.sum(1, keepdims=True) > 0, g, 1.0)
    return (p / p.sum(1, keepdims=True)).cumsum(1)


def _uniform_in(rng, t):
    """One uniform random point in each triangle t[m] (M, 3, 3)."""
    r1, r2 = np.sqrt(rng.random(len(t)))[:, None], rng.random(len(t))[:, None]
    return (1 - r1) * t[:, 0] + r1 * (1 - r2) * t[:, 1] + r1 * r2 * t[:, 2]


def _draw(rng, T, g, levels):
    """One random point per triangle T[m], drawn from the piecewise-constant density g[m] over its
    4^levels sub-triangles (uniform inside the chosen one); uniform where g[m] vanishes."""
    sub = _sub_triangles(T, levels)
    M, C = g.shape
    c = (_cdf(g) < rng.random((M, 1))).sum(1).clip(0, C - 1)
    return _uniform_in(rng, sub[np.arange(M), c])


def _draw_rows(rng, T, g, levels, counts):
    """For each triangle T[m], counts[m] random points from the density g[m] of :func:`_draw`,
    stratified: point d from the stratum [d, d + 1) / counts[m] of its cumulative distribution
    (as `--end-draws` does). A list of (counts[m], 3) arrays."""
    sub = _sub_triangles(T, levels)
    C = g.shape[1]
    cdf = _cdf(g)
    out = []
    for m, c in enumerate(counts):
        u = (np.arange(c) + rng.random(c)) / c
        cell = (cdf[m][None] < u[:, None]).sum(1).clip(0, C - 1)
        out.append(_uniform_in(rng, sub[m, cell]))
    return out


def _row_counts(e, light):
    """Rows per pair of estimator ``rows-M`` (M each) or ``alloc-M`` (M on average, each pair's
    share of the shooter's rows in proportion to the light it receives, ``light``, at least 1 and
    at most 64)."""
    mean = int(e.split("-")[1])
    if e.startswith("rows-") or light.sum() <= 0:
        return np.full(len(light), mean)
    return np.clip(np.rint(mean * len(light) * light / light.sum()), 1, 64).astype(np.int64)


def _on_lattice(T, y, D):
    """Integer barycentric weights (M, 3), summing to D, of a point of the 1/D lattice of
    triangle T[m] near y[m] (y on the triangle), every weight at least 1: an exact rational point
    strictly inside the triangle (a point on an edge would be blocked by the neighbour across it)."""
    e1, e2, d = T[:, 1] - T[:, 0], T[:, 2] - T[:, 0], y - T[:, 0]
    g11, g12, g22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    r1, r2 = (d * e1).sum(1), (d * e2).sum(1)
    det = g11 * g22 - g12 ** 2
    u = np.clip(np.rint((g22 * r1 - g12 * r2) / det * D), 1, D - 2).astype(np.int64)
    v = np.clip(np.rint((g11 * r2 - g12 * r1) / det * D), 1, D - 2).astype(np.int64)
    v = np.minimum(v, D - 1 - u)
    return np.stack([D - u - v, u, v], axis=1)


ESTIMATORS = {
    "centroid": "the render's: rays from i's K samples to j's centroid (reverse rays where it is behind i)",
    "pair-centroid": "one end point per pair: j's centroid weighted by the kernel summed over i",
    "sample-centroid": "one end point per ray: j's kernel-weighted centroid seen from that sample",
    "sample-centroid/21": "the same on the nearest point of j's 1/21 barycentric lattice (the board's D)",
    "KxK": "K x K rays to j's K sample points, each weighted by the point-to-point kernel",
    "cell-centroids": "4 end points per pair: each quarter of j's kernel-weighted centroid, weighted by its kernel mass",
    "KxK-sum": "K x K rays to j's K sample points, j's weighted by the kernel summed over i, i's by their point factor",
    "KxK-area": "K x K rays to j's K sample points, those in front of i's plane weighted equally (area), i's by their point factor",
    "pair-draw": "one end point per pair drawn at random from j's kernel density summed over i (seeded)",
    "pair-draw-k": "pair-draw with each ray weighted by the point-to-point kernel at its end point",
    "rows-M": "M rows per pair, row d drawn from stratum d of M of j's kernel density summed over i (--end-draws M)",
    "alloc-M": "rows-M with M rows per pair on average, shared among i's pairs in proportion to the light each "
               "receives (A_j F_ji; at least 1, at most 64)",
    "both-draw-k": "both-draw with each ray weighted by the point-to-point kernel at its end point",
    "both-draw": "i's K points drawn at random, one per stratum of equal area (shared by i's pairs), each weighted by "
                 "its point factor to j; one end point per pair drawn from j's kernel density summed over them",
}


def _end_kernel(x, n_i, y, T, n_j, D):
    """(J, K) point-to-point kernel from the shooter points x (K, 3) to each pair's end point
    (barycentric y (J, 3) over D on triangle T[m])."""
    Y = np.einsum("jc,jcd->jd", y / D, T)
    return _kernel(x[None], n_i, Y[:, None], n_j[:, None])


def _stratified(rng, T, K):
    """K random points of triangle T (3, 3), one uniform in each of K strata of equal area: the
    4^L sub-triangles (4^L >= K, element order) taken in K consecutive runs of equal length."""
    L = int(np.ceil(np.log(K) / np.log(4) - 1e-9))
    sub = _sub_triangles(T[None], L)[0]                  # (4^L, 3, 3)
    per = len(sub) // K
    return _uniform_in(rng, sub[np.arange(K) * per + rng.integers(0, per, K)])


def _study_scene(name):
    """block (a cube in a box, 60 patches), slab (a slab on a box's floor, cut along its contact
    lines) or a closed_scenes name prefix."""
    if name == "block":
        return box_with_block()
    if name == "slab":
        from blockray.host_driver.scene.contact import split_contacts
        return split_contacts(closed_box_with_slab())[0]
    return next(s for n, s in closed_scenes() if n.startswith(name))


def rules(args):
    """Energy balance of closed scenes rendered with each --end-points rule (the render's own
    path: host, board, Jacobi), draw over several seeds."""
    print("| scene | patches | rule | absorbed / emitted - 1 (R, G, B) | rays | seconds |")
    print("|---|---|---|---|---|---|")
    for name in args.scenes:
        scene = _study_scene(name)
        runs = [(r, 0) for r in args.rules if r != "draw"] + [("draw", s) for s in range(args.seeds) if "draw" in args.rules]
        for rule, seed in runs:
            t = time.perf_counter()
            drawn = args.sample_points != "fixed"
            ends = {"end_lattice": args.end_lattice if rule != "centroid" or drawn else 1,
                    "end_draws": args.end_draws if rule == "draw" else 1,
                    "emitter_factor": args.emitter_factor if rule == "draw" else 1}
            res = render(scene, backend=args.board, solver="jacobi", tolerance=args.tolerance, end_points=rule,
                         end_seed=seed, sample_points=args.sample_points, sample_seed=seed, **ends)
            bal = absorbed_balance(scene, res.radiosity)
            label = res.report["end_points"] + (f"; samples {res.report['sample_points']}" if drawn else "")
            print(f"| {name} | {scene.patches} | {label} | " + ", ".join(f"{100 * x:+.3f}%" for x in bal)
                  + f" | {res.report['rays']} | {time.perf_counter() - t:.0f} |", flush=True)


def shooters(args):
    """The shooters carrying the most imbalance (``A_i B_i (s_i - 1)``) in a render (Jacobi, the
    given --end-points and --sample-points), and each one's row sum s_i re-estimated with Embree
    (embreex): the exact factors times the weighted clear fraction of rays from K shooter points
    to one uniform random point per receiver, with the fixed pattern and with stratified random
    points of ``--sample-points draw`` (SampleScheme, mean over --draws seeds). In a closed scene s_i
    should be 1."""
    from blockray.host_driver.scene.builtin import NAMES, load_scene
    from blockray.host_driver.traverse.peer import embree_occluded
    from blockray.samples import SampleScheme
    scene = load_scene(args.scene) if args.scene in NAMES else _study_scene(args.scene)
    opts = dict(end_points=args.end_points, end_lattice=args.end_lattice, sample_points=args.sample_points,
                end_draws=args.end_draws, end_seed=args.render_seed, sample_seed=args.render_seed,
                emitter_factor=args.emitter_factor)
    res = render(scene, solver="jacobi", tolerance=1e-6, **opts)
    s_i, B, A = res.solve.row_sums.shot, res.radiosity, scene.areas
    emitted = (scene.emission * A[:, None]).sum(0)
    print(f"render {opts}: absorbed / emitted - 1 {np.round(100 * np.array(res.report['absorbed_balance']), 3)} %")
    rng = np.random.default_rng(args.seed)
    V, N = scene.patch_vertices, scene.normals / np.linalg.norm(scene.normals, axis=1)[:, None]

    def row_sum(i, X, rec, f):
        Y = _uniform_in(rng, V[rec])
        P, Q = np.repeat(X[None], len(rec), 0).reshape(-1, 3), np.repeat(Y, len(X), 0)
        w = _kernel(P, N[i], Q, N[np.repeat(rec, len(X))]).reshape(len(rec), len(X))
        hit = embree_occluded(scene, P + 2e-5 * N[i], Q + 2e-5 * N[np.repeat(rec, len(X))], eps=1e-9)[0]
        clear = (w * ~hit.reshape(w.shape)).sum(1) / np.where(w.sum(1) > 0, w.sum(1), 1)
        return (f * np.where(w.sum(1) > 0, clear, 1.0)).sum()

    share = A * B[:, 0] * (s_i - 1) / emitted[0]
    print("| shooter | group | share of the R balance | render s_i - 1 | Embree, fixed points | Embree, stratified random (mean +- s.e.) |")
    print("|---|---|---|---|---|---|")
    for i in np.argsort(-np.abs(share))[:args.top]:
        f_all = ff.unoccluded_factors(scene, i)
        rec = np.flatnonzero(f_all > 0)
        f = A[rec] * f_all[rec] / A[i]
        fixed = row_sum(i, SampleScheme(8).points(V[i][None])[0], rec, f) - 1
        drawn = [row_sum(i, SampleScheme(8, args.end_lattice, seed=args.seed * 1000 + d).points(V[i][None], [i])[0],
                         rec, f) - 1 for d in range(args.draws)]            # the render's own drawn points
        print(f"| {i} | {scene.group_names[scene.group[i]]} | {100 * share[i]:+.4f}% | {s_i[i] - 1:+.4f} | {fixed:+.4f} "
              f"| {np.mean(drawn):+.4f} +- {np.std(drawn, ddof=1) / np.sqrt(len(drawn)):.4f} |", flush=True)


def estimators(args):
    """Energy balance of an occluded closed scene with each visibility estimator of ESTIMATORS:
    the exact factor F_ji times a weighted clear fraction (weights: each shooter sample's point
    factor to j, formfactor.sample_weights; KxK: the point-to-point kernel), rays decided by the
    exact predicate over every patch (exact_float.blocked_rays), Jacobi to 1e-9."""
    from blockray.exact_float import blocked_rays
    from blockray.host_driver.radiosity.solver import jacobi
    from blockray.samples import SampleScheme
    scene = _study_scene(args.scene)
    K, levels = args.samples, 3
    samples = SampleScheme(K)
    W = np.asarray(samples.weights, dtype=np.int64)
    V, A, nrm, N = scene.patch_vertices, scene.areas, scene.normals, scene.patches
    X, SP, SPi = samples.points(V), _sub_centroids(V, levels), _sub_centroids(V, args.shooter_levels)
    fine = 3 * 2 ** 24                                   # end points exact on j's plane, about 1e-7 of it off y
    rng = np.random.default_rng(args.seed)
    print(f"seed={args.seed}")

    def clear(i, P_w, j, Q_w):
        """(len(Q_w), len(P_w)) clear bits: from i's points P_w to j's points Q_w (barycentric)."""
        return ~blocked_rays(np.repeat(V[i][None], len(P_w), axis=0), P_w, np.repeat(V[j][None], len(Q_w), axis=0),
                             Q_w, V)

    F = np.zeros((N, N))
    for i in range(N):
        F[:, i] = ff.unoccluded_factors(scene, i)
    print(f"{scene.name}: {N} patches, K = {K}; exact factors done", flush=True)
    out = {e: np.zeros((N, N)) for e in args.which}
    rays = dict.fromkeys(args.which, 0)
    for i in range(N):
        J = np.flatnonzero(F[:, i] > 0)
        if not len(J):
            continue
        w = ray_weights.pair_sample_weights(scene, samples, np.full(len(J), i), J)                      # (J, K)
        front = ray_weights.centroid_in_front(scene, i, J)
        for e in args.which:
            bits = np.zeros((len(J), K))
            weights = w
            if e == "centroid":
                for m, j in enumerate(J):
                    if front[m]:
                        bits[m] = clear(i, W, j, [[1, 1, 1]])[0]
                weights = w.copy()
                for m in np.flatnonzero(~front):                                             # reverse rays
                    j = J[m]
                    bits[m] = clear(j, W, i, [[1, 1, 1]])[0]
                    weights[m] = ray_weights.pair_sample_weights(scene, samples, [j], [i])[0]
            elif e.startswith("pair-centroid"):
                g = _kernel(SPi[i][None, :, None], nrm[i], SP[J][:, None], nrm[J][:, None, None]).sum(axis=1)
                # (a pair whose kernel vanishes at every cubature point keeps j's centroid)
                total = g.sum(1)[:, None]
                y = np.where(total > 0, (g[..., None] * SP[J]).sum(1) / np.where(total > 0, total, 1), SP[J].mean(1))
                y = _on_lattice(V[J], y, int(e.split("/")[1]) if "/" in e else fine)
                for m in range(len(J)):
                    bits[m] = clear(i, W, J[m], y[m][None])[0]
            elif e.startswith("sample-centroid"):
                g = _kernel(X[i][None, :, None], nrm[i], SP[J][:, None], nrm[J][:, None, None])     # (J, K, M)
                total = g.sum(2)[..., None]
                y = np.where(total > 0, (g[..., None] * SP[J][:, None]).sum(2) / np.where(total > 0, total, 1),
                             SP[J].mean(1)[:, None])
                y = _on_lattice(np.repeat(V[J], K, axis=0), y.reshape(-1, 3),
                                21 if e.endswith("/21") else fine).reshape(len(J), K, 3)
                for m in range(len(J)):
                    for k in range(K):
                        bits[m, k] = clear(i, W[k:k + 1], J[m], y[m, k][None])[0, 0]
            elif e.startswith("pair-draw"):
                g = _kernel(SPi[i][None, :, None], nrm[i], SP[J][:, None], nrm[J][:, None, None]).sum(axis=1)
                y = _draw(rng, V[J], g, levels)
                y = _on_lattice(V[J], y, int(e.split("/")[1]) if "/" in e else fine)
                for m in range(len(J)):
                    bits[m] = clear(i, W, J[m], y[m][None])[0]
                if e == "pair-draw-k":
                    weights = _end_kernel(X[i], nrm[i], y, V[J], nrm[J], y.sum(1)[0])
            elif e.startswith(("rows-", "alloc-")):
                g = _kernel(SPi[i][None, :, None], nrm[i], SP[J][:, None], nrm[J][:, None, None]).sum(axis=1)
                counts = _row_counts(e, A[J] * F[J, i])
                rays[e] += int(counts.sum()) * K
                v = np.zeros(len(J))
                for m, y in enumerate(_draw_rows(rng, V[J], g, levels, counts)):
                    b = clear(i, W, J[m], _on_lattice(np.repeat(V[J[m]][None], len(y), axis=0), y, fine))  # (rows, K)
                    v[m] = (w[m] * b).sum() / (len(y) * w[m].sum()) if w[m].sum() > 0 else b.mean()
                out[e][J, i] = F[J, i] * v
                continue
            elif e.startswith("both-draw"):
                x = _stratified(rng, V[i], K)
                P_w = _on_lattice(np.repeat(V[i][None], K, axis=0), x, fine)
                x = np.einsum("kc,cd->kd", P_w / fine, V[i])
                g = _kernel(x[None, :, None], nrm[i], SP[J][:, None], nrm[J][:, None, None]).sum(axis=1)
                y = _on_lattice(V[J], _draw(rng, V[J], g, levels), fine)
                pf = np.stack([point_factor.point_to_triangles(x[k], nrm[i], V[J]) for k in range(K)], axis=1)
                ahead = ((x[None] - V[J][:, :1]) * nrm[J][:, None]).sum(-1) > 0          # (J, K)
                weights = np.where(ahead, pf, 0.0)
                for m in range(len(J)):
                    bits[m] = clear(i, P_w, J[m], y[m][None])[0]
                if e == "both-draw-k":
                    weights = _end_kernel(x, nrm[i], y, V[J], nrm[J], fine)
            elif e == "cell-centroids":     # 4 end points: each quarter of j's kernel centroid and mass
                g = _kernel(SPi[i][None, :, None], nrm[i], SP[J][:, None], nrm[J][:, None, None]).sum(axis=1)
                cell = np.arange(SP.shape[1]) // 4 ** (levels - 1)   # _sub_centroids' order: the first cut outermost
                v = np.zeros(len(J))
                for m in range(len(J)):
                    mass = np.array([g[m, cell == q].sum() for q in range(4)])
                    y = np.array([(g[m, cell == q, None] * SP[J[m], cell == q]).sum(0) / mass[q] if mass[q] > 0
                                  else SP[J[m], cell == q].mean(0) for q in range(4)])
                    b = clear(i, W, J[m], _on_lattice(np.repeat(V[J[m]][None], 4, axis=0), y, fine))   # (4, K)
                    weight = w[m][None, :] * mass[:, None]
                    v[m] = (weight * b).sum() / weight.sum() if weight.sum() > 0 else b.mean()
                out[e][J, i] = F[J, i] * v
                continue
            elif e.startswith("KxK"):
                Y = X[J]
                g = _kernel(X[i][None, :, None], nrm[i], Y[:, None], nrm[J][:, None, None])       # (J, K, K)
                if e == "KxK-area":         # j's points in front of i's plane, equally
                    ahead = np.array([ray_weights.samples_in_front(scene, samples, j, [i])[0] for j in J], dtype=float)
                    g = w[:, :, None] * ahead[:, None, :]
                elif e == "KxK-sum":        # j's points by the kernel summed over i
                    u = _kernel(SPi[i][None, :, None], nrm[i], Y[:, None], nrm[J][:, None, None]).sum(axis=1)
                    g = w[:, :, None] * u[:, None, :]
                v = np.zeros(len(J))
                for m in range(len(J)):
                    b = clear(i, W, J[m], W).T                                                   # (K, K)
                    v[m] = (g[m] * b).sum() / g[m].sum() if g[m].sum() > 0 else b.mean()
                out[e][J, i] = F[J, i] * v
                continue
            total = weights.sum(1)
            v = np.where(total > 0, (weights * bits).sum(1) / np.where(total > 0, total, 1), bits.mean(1))
            out[e][J, i] = F[J, i] * v
    for e in args.which:
        sums = (A[:, None] * out[e]).sum(axis=0) / A - 1
        B = jacobi(scene, out[e], tolerance=1e-9, max_iterations=5000).B
        bal = absorbed_balance(scene, B)
        print(f"| {e} | {', '.join(f'{100 * b:+.3f}%' for b in bal)} | {np.average(sums, weights=A):+.2e} "
              f"({sums.min():+.2e}, {sums.max():+.2e}) |" + (f" {rays[e]} rays |" if rays[e] else ""), flush=True)


def row_sums(args):
    """Visible row sums sum_j F_ij v_ij / 1 - 1 of the box's shooters in the icosphere scene, with
    the render's visibility (render.shoot's rule) at a given shooter sample count."""
    from blockray.host_driver.render.render import make_board, Visibility
    from blockray.host_driver.traverse.voxel import VoxelGrid
    from blockray.host_driver.traverse.cost import default_voxels
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
        p = BoardParams(bits=None)
        vis = Visibility(scene, board, grid, samples, rows=p.rows, cols=p.cols)
        rows = []
        for i in range(0, 192, 6):                          # every 6th triangle of the box
            f = ff.unoccluded_factors(scene, i)
            rec = np.flatnonzero(f > 0)
            direct = ray_weights.centroid_in_front(scene, i, rec)
            v = np.empty(len(rec))
            weigh = ray_weights.sample_weights if args.kernel else (
                lambda sc, sa, a, b: ray_weights.samples_in_front(sc, sa, a, b).astype(float))
            v[direct] = vis.clear_fraction(i, rec[direct], weigh(scene, samples, i, rec[direct]))
            for m in np.flatnonzero(~direct):
                j = rec[m]
                v[m] = vis.clear_fraction(j, np.array([i]), weigh(scene, samples, j, [i]))[0]
            rows.append((A[rec] * f[rec] * v).sum() / A[i] - 1)
        rows = np.array(rows)
        print(f"K = {K}, {'kernel-weighted' if args.kernel else 'uniform'} rays: {len(rows)} box shooters, row sum - 1: mean {rows.mean():+.2e}, "
              f"min {rows.min():+.2e}, max {rows.max():+.2e}", flush=True)


def speed(args):
    from blockray import threads
    from blockray.host_driver.scene.builtin import load_scene
    for name in args.scenes:
        scene = load_scene(name)
        V = scene.patch_vertices
        masks = [np.flatnonzero(ff.exchange_mask(scene, i)) for i in range(0, scene.patches, args.step)]
        I = np.concatenate([np.full(len(j), i) for i, j in zip(range(0, scene.patches, args.step), masks)])
        J = np.concatenate(masks)
        S, R = V[I], V[J]
        ff.pair_factors(S[:4], R[:4])                        # load the compiled kernels
        row = {"scene": name, "pairs": len(I)}
        with threads.using(1):
            for label, target in (("closed_form", 0.0), ("default", ff.FAR_TARGET)):
                used = np.zeros(len(ff.METHODS), dtype=np.int64)
                c0 = time.process_time()
                ff.pair_factors(S, R, target=target, stats=used)
                row[f"{label}_cpu_us_per_pair"] = round((time.process_time() - c0) / len(I) * 1e6, 3)
                row[f"{label}_methods"] = dict(zip(ff.METHODS, used.tolist()))
            row["default_cpu_us_per_pair_by_method"] = by_method(S, R)
        from pyviewfactor.pvf_integrators import compute_viewfactor_sa30
        n = min(args.peer_pairs, len(I))
        c0 = time.process_time()
        for k in range(n):
            compute_viewfactor_sa30(np.ascontiguousarray(R[k]), np.ascontiguousarray(S[k]), 4 * np.pi)
        row["pyviewfactor_sa30_cpu_us_per_pair"] = round((time.process_time() - c0) / n * 1e6, 1)
        M = np.array([ff.exchange_mask(scene, i) for i in range(scene.patches)])
        row["render_pairs_ordered"] = int(M.sum())                           # every column in full
        row["render_pairs_unordered"] = int(np.triu(M | M.T).sum())          # each pair once
        print(row, flush=True)


def by_method(S, R):
    """CPU us per pair of the default pair kernel, the pairs grouped by the method that decided
    each (one kernel call per group, on the calling threads)."""
    methods = np.zeros((len(S), len(ff.METHODS)), dtype=np.int64)
    ff._pairs(S, R, ff.FAR_TARGET, np.zeros(len(S)), methods)
    decided = methods.argmax(axis=1)
    out = {}
    for k, name in enumerate(ff.METHODS):
        pick = np.flatnonzero(decided == k)
        if len(pick):
            Si, Ri = np.ascontiguousarray(S[pick]), np.ascontiguousarray(R[pick])
            c0 = time.process_time()
            ff._pairs(Si, Ri, ff.FAR_TARGET, np.zeros(len(pick)), np.zeros((len(pick), len(ff.METHODS)), dtype=np.int64))
            out[name] = {"pairs": len(pick), "cpu_us_per_pair": round((time.process_time() - c0) / len(pick) * 1e6, 2)}
    return out


def grazing(args):
    from blockray.host_driver.scene.builtin import load_scene
    scene = load_scene("cornell")
    V = scene.patch_vertices
    I, J = [], []
    for i in range(scene.patches):
        j = np.flatnonzero(ff.exchange_mask(scene, i))
        j = j[j > i]
        I.append(np.full(len(j), i))
        J.append(j)
    I, J = np.concatenate(I), np.concatenate(J)
    S, R = V[I], V[J]
    ci, cj = S.mean(axis=1), R.mean(axis=1)
    D = np.linalg.norm(cj - ci, axis=1)
    d = (cj - ci) / D[:, None]
    ni = np.cross(S[:, 1] - S[:, 0], S[:, 2] - S[:, 0])
    nj = np.cross(R[:, 1] - R[:, 0], R[:, 2] - R[:, 0])
    cos_i = np.einsum("mc,mc->m", ni / np.linalg.norm(ni, axis=1)[:, None], d)
    cos_j = -np.einsum("mc,mc->m", nj / np.linalg.norm(nj, axis=1)[:, None], d)
    unclipped = (np.einsum("mkc,mc->mk", R - S[:, :1], ni) >= 0).all(axis=1) & \
        (np.einsum("mkc,mc->mk", S - R[:, :1], nj) >= 0).all(axis=1)
    g = np.minimum(cos_i, cos_j)
    chosen = (g < args.cosine) & (np.minimum(np.abs(cos_i), np.abs(cos_j)) > 1e-12) & (D > args.distance)
    rng = np.random.default_rng(args.seed)
    print(f"seed={args.seed}; {len(I)} unordered pairs, {chosen.sum()} grazing")
    for label, m in (("unclipped", unclipped), ("clipped", ~unclipped)):
        idx = np.flatnonzero(chosen & m)
        pick = rng.choice(idx, size=min(args.pairs, len(idx)), replace=False)
        closed = ff.pair_factors(S[pick], R[pick], target=0.0)
        used = np.zeros(len(ff.METHODS), dtype=np.int64)
        default = ff.pair_factors(S[pick], R[pick], stats=used)
        err_c, err_d = [], []
        for k, m_ in enumerate(pick):
            P, Q = clip_front(R[m_], S[m_]), clip_front(S[m_], R[m_])
            if len(P) < 3 or len(Q) < 3:
                continue
            oracle = contour_oracle(P, Q, dps=30)
            err_c.append(abs(closed[k] / oracle - 1))
            err_d.append(abs(default[k] / oracle - 1))
            print(f"{label} ({I[m_]}, {J[m_]}): closed form {err_c[-1]:.1e}, default {err_d[-1]:.1e}", flush=True)
        print(f"**{label}: {len(err_c)} of {len(idx)} pairs; closed form worst {max(err_c):.2e} median "
              f"{np.median(err_c):.1e}; default worst {max(err_d):.2e} median {np.median(err_d):.1e}; "
              f"default picks {dict(zip(ff.METHODS, used.tolist()))}", flush=True)


def _every_step_pairs(scene, step):
    rows = list(range(0, scene.patches, step))
    masks = [np.flatnonzero(ff.exchange_mask(scene, i)) for i in rows]
    I = np.concatenate([np.full(len(j), i) for i, j in zip(rows, masks)])
    return I, np.concatenate(masks)


def trigger(args):
    """The closed form's actual error (mpmath) against its estimate u S / F on pairs that trigger
    the recomputation (64 u S > FAR_TARGET F)."""
    from blockray.host_driver.scene.builtin import load_scene
    V = load_scene("cornell").patch_vertices
    I, J = _every_step_pairs(load_scene("cornell"), 8)
    rng = np.random.default_rng(args.seed)
    print(f"seed={args.seed}")
    ratios = []
    for k in rng.permutation(len(I)):
        P, Q = clip_front(V[J[k]], V[I[k]]), clip_front(V[I[k]], V[J[k]])
        if len(P) < 3 or len(Q) < 3:
            continue
        P4, Q4 = np.zeros((4, 3)), np.zeros((4, 3))
        P4[:len(P)], Q4[:len(Q)] = P, Q
        value, size, _, _ = closed_form._contour(P4, len(P), Q4, len(Q), closed_form.EDGE_TARGET)
        if value == 0.0:
            continue
        estimate = 2.0 ** -53 * size / value
        if not 64 * estimate > ff.FAR_TARGET or estimate > 1e-3:     # not triggered; or coplanar to rounding
            continue
        error = abs(value / contour_oracle(P, Q, dps=30) - 1)
        ratios.append(error / estimate)
        print(f"({I[k]}, {J[k]}): u S / F {estimate:.1e}, closed form's error {error:.1e}, ratio {ratios[-1]:.2f}", flush=True)
        if len(ratios) == args.pairs:
            break
    print(f"**ratio of error to estimate over {len(ratios)} pairs: min {min(ratios):.2f}, median {np.median(ratios):.2f}, max {max(ratios):.2f}")


def versus(args):
    """Speed and the unoccluded radiosity of each scene, the earlier module against this one."""
    for name in args.scenes:
        _versus(name)


def _versus(name):
    from blockray import threads
    from blockray.host_driver import _formfactor_before as old
    from blockray.host_driver.scene.builtin import load_scene
    scene = load_scene(name)
    V, N = scene.patch_vertices, scene.patches
    I, J = _every_step_pairs(scene, 8)
    S, R = V[I], V[J]
    print(f"speed: {len(I)} pairs of every 8th {name} shooter, one thread")
    for m in (old, ff):
        m.pair_factors(S[:4], R[:4])
    with threads.using(1):
        for _ in range(2):
            for version, m in (("before", old), ("now", ff)):
                for label, target in (("closed form", 0.0), ("default", m.FAR_TARGET)):
                    used = np.zeros(len(m.METHODS), dtype=np.int64)
                    c0 = time.process_time()
                    m.pair_factors(S, R, target=target, stats=used)
                    print(f"{version} {label}: {(time.process_time() - c0) / len(I) * 1e6:.2f} us/pair",
                          dict(zip(m.METHODS, used.tolist())), flush=True)
    # unoccluded radiosity: the visibility multiplies both alike
    M = np.array([ff.exchange_mask(scene, i) for i in range(N)])
    I, J = np.nonzero(np.triu(M | M.T, 1))
    B = {}
    for label, m in (("before", old), ("now", ff)):
        AF = np.zeros((N, N))
        AF[I, J] = AF[J, I] = m.pair_factors(V[I], V[J])
        F = np.where(M.T, AF / scene.areas[:, None], 0.0)            # F[j, i]: receiver j, shooter i
        B[label] = np.stack([np.linalg.solve(np.eye(N) - scene.reflectance[:, c][:, None] * F, scene.emission[:, c])
                            for c in range(3)], axis=1)
    lit = B["before"] > 1e-12 * B["before"].max()
    rel = np.abs(B["now"][lit] / B["before"][lit] - 1)
    print(f"**{name} unoccluded radiosity, {len(I)} unordered pairs: relative change of B max {rel.max():.2e}, "
          f"RMS {np.sqrt(np.mean(rel ** 2)):.2e}")


def unresolved(args):
    """The pairs of every 8th shooter that no route certifies within FAR_TARGET (method
    "unresolved"): how many, their largest F, and the worst four against the mpmath oracle."""
    from blockray.host_driver.scene.builtin import load_scene
    for name in args.scenes:
        scene = load_scene(name)
        V, A = scene.patch_vertices, scene.areas
        I, J = _every_step_pairs(scene, 8)
        methods = np.zeros((len(I), len(ff.METHODS)), dtype=np.int64)
        AF = ff._pairs(np.ascontiguousarray(V[I]), np.ascontiguousarray(V[J]), ff.FAR_TARGET, methods)
        q = np.flatnonzero(methods[:, ff.METHODS.index("unresolved")] > 0)
        F = AF[q] / np.minimum(A[I[q]], A[J[q]])
        print(f"{name}: {scene.patches} patches, {len(I)} pairs, unresolved {len(q)}, largest F "
              f"{F.max() if len(q) else 0:.2e}", flush=True)
        for k in q[np.argsort(-F)[:4]]:
            P, Q = clip_front(V[J[k]], V[I[k]]), clip_front(V[I[k]], V[J[k]])
            oracle = contour_oracle(P, Q, dps=30) if len(P) > 2 and len(Q) > 2 else 0.0
            print(f"  pair {I[k]}, {J[k]}: F {AF[k] / min(A[I[k]], A[J[k]]):.2e}, against mpmath "
                  f"{AF[k] / oracle - 1 if oracle else float('nan'):+.1e}", flush=True)


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
    ch.add_argument("--worst", type=int, default=0, metavar="N", help="also list the N patches that change most")
    ch.add_argument("ref", help="reference radiosity: --patches CSV or .npy")
    ch.add_argument("new", help="radiosity compared with it")
    en = sub.add_parser("ends")
    en.add_argument("--samples", type=int, default=8)
    es = sub.add_parser("estimators")
    es.add_argument("--scene", default="block", help="block (a cube in a box, 60 patches), slab (a slab on a box's "
                    "floor, cut along its contact lines) or a closed_scenes prefix")
    es.add_argument("--samples", type=int, default=8)
    es.add_argument("--which", nargs="+", default=[e for e in ESTIMATORS if not e.endswith("-M")] + ["rows-4", "alloc-4"],
                    help=f"of {', '.join(ESTIMATORS)} (M a number); pair-centroid/N: on j's 1/N barycentric lattice")
    es.add_argument("--seed", type=int, default=1, help="pair-draw's random end points")
    es.add_argument("--shooter-levels", type=int, default=3,
                    help="pair-centroid: the kernel summed over 4^L points of the shooter (and 64 of j)")
    ru = sub.add_parser("rules")
    ru.add_argument("scenes", nargs="*", default=["block", "slab", "icosphere"])
    ru.add_argument("--board", default="model")
    ru.add_argument("--seeds", type=int, default=3, help="draw: seeds 0 .. N-1")
    ru.add_argument("--rules", nargs="+", default=["centroid", "kernel", "draw"])
    ru.add_argument("--tolerance", type=float, default=1e-6)
    ru.add_argument("--end-draws", type=int, default=1, help="draw: rows per pair")
    ru.add_argument("--emitter-factor", type=int, default=1, help="draw: times the rows from an emitting shooter")
    ru.add_argument("--end-lattice", type=int, default=1, help="kernel, draw: the end-point lattice's refinement")
    ru.add_argument("--sample-points", default="fixed", choices=["fixed", "draw", "rows"],
                    help="the shooters' samples (draw, rows: seeded like the end points, seed N for run N)")
    r = sub.add_parser("rows")
    r.add_argument("--samples", type=int, nargs="+", default=[8, 32])
    r.add_argument("--kernel", action="store_true", help="weigh rays by formfactor.sample_weights")
    sh = sub.add_parser("shooters")
    sh.add_argument("scene", nargs="?", default="room")
    sh.add_argument("--top", type=int, default=12)
    sh.add_argument("--draws", type=int, default=24, help="seeds of drawn shooter points")
    sh.add_argument("--seed", type=int, default=7)
    sh.add_argument("--end-points", default="draw")
    sh.add_argument("--end-lattice", type=int, default=8)
    sh.add_argument("--sample-points", default="fixed", choices=["fixed", "draw", "rows"])
    sh.add_argument("--end-draws", type=int, default=1, help="the render's rows per pair")
    sh.add_argument("--emitter-factor", type=int, default=1, help="the render's --emitter-factor")
    sh.add_argument("--render-seed", type=int, default=0, help="the render's end and sample seed")
    sp = sub.add_parser("speed")
    sp.add_argument("scenes", nargs="*", default=["cornell", "room"])
    sp.add_argument("--step", type=int, default=8, help="every step-th shooter's pairs")
    sp.add_argument("--peer-pairs", type=int, default=2000, help="pairs for pyviewfactor")
    gr = sub.add_parser("grazing")
    gr.add_argument("--pairs", type=int, default=40, help="pairs per kind (unclipped, clipped)")
    gr.add_argument("--seed", type=int, default=2017)
    gr.add_argument("--cosine", type=float, default=1e-3)
    gr.add_argument("--distance", type=float, default=300.0)
    tr = sub.add_parser("trigger")
    tr.add_argument("--pairs", type=int, default=30)
    tr.add_argument("--seed", type=int, default=3)
    un = sub.add_parser("unresolved")
    un.add_argument("scenes", nargs="*", default=["cornell", "room"])
    vs = sub.add_parser("versus")
    vs.add_argument("scenes", nargs="*", default=["cornell"])
    args = ap.parse_args(argv)
    print_run_header()
    {"table": table, "energy": energy, "rows": row_sums, "speed": speed, "grazing": grazing, "trigger": trigger,
     "versus": versus, "unresolved": unresolved, "closure": closure, "boards": boards, "change": change, "ends": end_points,
     "estimators": estimators, "rules": rules, "shooters": shooters}[args.what](args)


if __name__ == "__main__":
    main()

"""Bit-exact model: a million queries against the independent exact evaluation, throughput, and
agreement with the float64 golden board by B.

    python benchmarks/bench_model.py                       # all three parts, default sizes
    python benchmarks/bench_model.py --queries 1000000 --part exact
    python benchmarks/bench_model.py --part throughput
    python benchmarks/bench_model.py --part float --scene cornell
    python benchmarks/bench_model.py --part render --scene cornell --max-shots 40   # B = 10..20 table

``exact``: every query (ray, patch) is decided by the model's arithmetic (blocked_block, the
shared-term int64 split) and by :func:`blockray.exact.blocked_reference` (Python integers,
orient3d); each batch is also run as a command stream through :class:`BoardModel` and its OR'd
bits compared. Queries come from quantised random scenes (real sample points and centroids at a
random B), closed meshes with rays through shared vertices and edges, and hard random triangles
(extreme coordinates, end points on vertices/edges, rays through vertices/edges, in-plane rays,
collinear triangles). Prints the number of queries, disagreements (must be 0) and rates.
"""

import argparse
import itertools
import platform
import sys
import time
from types import SimpleNamespace

import numpy as np

from blockray.exact import blocked_block, blocked_reference, patch_normals
from blockray.params import BoardParams
from blockray.samples import SampleScheme
from blockray.protocol import BeginBlock, EndBlock, LoadReceiver, LoadShooter, Voxel
from blockray.sim.model import BoardModel, ModelBoard
from blockray.board import BlockRay

import _shared  # noqa: F401  (tests/ on the path: the tests' scenes)
from scenes import mesh_scene


# -- query batches: (P (S,3), Q (R,3), V (N,3,3), bits) ------------------------------------------

def batch_scene(rng):
    """Real model inputs: a random float scene quantised at a random B."""
    from blockray.fixedpoint import quantise
    n = 24
    centres = rng.random((n, 1, 3)) * 10
    v = centres + (rng.random((n, 3, 3)) - 0.5) * rng.choice([0.05, 1, 4])
    scene = mesh_scene(v.reshape(-1, 3), np.arange(3 * n), name="bench")
    s = SampleScheme(8)
    bits = int(rng.integers(s.denominator.bit_length() + 1, 21))
    q = quantise(scene, s, bits)
    i = rng.integers(0, n, 8)
    k = rng.integers(0, 8, 8)
    return q.shooters[i, k], q.receivers[rng.integers(0, n, 8)], q.vertices, bits


def _mesh():
    c = np.array([1 << 19] * 3)
    cube = np.array([c - 500 + 1000 * np.array(p) for p in itertools.product((0, 1), repeat=3)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([t for a, b, c_, d in quads for t in ((a, b, c_), (a, c_, d))])
    return cube, faces


CUBE = _mesh()


def batch_mesh(rng):
    """Rays from inside a closed cube through its vertices, edge points and face points."""
    v, faces = CUBE
    inner = v.mean(axis=0).astype(np.int64)
    P = inner + rng.integers(-100, 101, (8, 3))
    Q = []
    for r in range(8):
        f = faces[rng.integers(len(faces))]
        a = rng.integers(0, 3, 3) * rng.integers(0, 2, 3)
        if a.sum() == 0:
            a[rng.integers(3)] = 1
        num, den = a @ v[f], int(a.sum())
        Q.append(P[r] + 2 * (num - den * P[r]))      # through num/den, on the surface
    return P, np.array(Q), v[faces], 20


def batch_hard(rng):
    bits = int(rng.integers(4, 21))
    L = (1 << bits) - 1

    def pts(n, central=False):
        lo, hi = (L // 3, 2 * L // 3) if central else (0, L)
        mode = rng.integers(0, 3, (n, 3))
        ext = rng.choice([0, 1, L - 1, L], (n, 3))
        mid = L // 2 + rng.integers(-3, 4, (n, 3))
        uni = rng.integers(lo, hi + 1, (n, 3))
        out = np.where(mode == 0, uni, np.where(mode == 1, ext, mid))
        return np.clip(np.where(central, uni, out), 0, L)

    N = 16
    V = np.concatenate([pts(3 * (N // 2)), pts(3 * (N // 2), central=True)]).reshape(N, 3, 3)
    coll = rng.random(N) < 0.15
    V[coll, 2] = np.clip(2 * V[coll, 1] - V[coll, 0], 0, L)               # collinear / zero area
    P = pts(8, central=True)
    P[:2] = V[N // 2 + rng.integers(0, N // 2, 2), rng.integers(0, 3, 2)]   # P on a vertex
    e = V[N // 2 + rng.integers(0, N // 2)]
    if ((e[0] + e[1]) % 2 == 0).all():
        P[2] = (e[0] + e[1]) // 2                                          # P on an edge
    Q = pts(8)
    for r in range(8):
        t = V[N // 2 + rng.integers(0, N // 2)]
        kind = rng.integers(0, 4)
        if kind == 0:
            Q[r] = 2 * t[rng.integers(3)] - P[r]                           # through a vertex
        elif kind == 1:
            k = rng.integers(3)
            Q[r] = t[k] + t[(k + 1) % 3] - P[r]                            # through an edge midpoint
        elif kind == 2:
            Q[r] = t[0] + t[1] - t[2]                                      # in the plane of t
    Q = np.clip(Q, 0, L)
    return P, Q, V, bits


def check_batch(P, Q, V, bits):
    """Disagreements of one batch: per query (blocked_block vs reference) and per ray (BoardModel)."""
    n = patch_normals(V)
    per = blocked_block(P, Q, V, n)
    Pl, Ql, Vl = P.tolist(), Q.tolist(), V.tolist()
    ref = np.array([[[blocked_reference(p, q, *t) for t in Vl] for p in Pl] for q in Ql], dtype=bool)
    bad = int((per != ref).sum())
    params = BoardParams(rows=len(Q), cols=len(P), boards=1, bits=bits, patch_depth=len(V), voxel_depth=1)
    bm = BoardModel(params)
    bm.load_memory(V, n, [0], [len(V)])
    cmds = ([BeginBlock()] + [LoadReceiver(r, tuple(q)) for r, q in enumerate(Ql)]
            + [LoadShooter(s, tuple(p)) for s, p in enumerate(Pl)]
            + [Voxel(0), EndBlock()])
    bad_rays = int((bm.execute(cmds).blocked[0] != ref.any(axis=2)).sum())
    return per.size, bad, bad_rays, int(ref.sum())


def part_exact(queries, seed):
    rng = np.random.default_rng(seed)
    print(f"exact: seed={seed}, target {queries} queries")
    kinds = {"scene": batch_scene, "mesh": batch_mesh, "hard": batch_hard}
    stats = {k: [0, 0, 0, 0] for k in kinds}
    t0 = time.perf_counter()
    total = 0
    while total < queries:
        for name, fn in kinds.items():
            n, bad, bad_rays, blocked = check_batch(*fn(rng))
            s = stats[name]
            s[0] += n; s[1] += bad; s[2] += bad_rays; s[3] += blocked
            total += n
    dt = time.perf_counter() - t0
    for name, (n, bad, bad_rays, blocked) in stats.items():
        print(f"  {name:6s} queries {n:9d}  blocked {blocked / n:6.2%}  disagreements {bad}  ray disagreements {bad_rays}")
    bad = sum(s[1] + s[2] for s in stats.values())
    print(f"exact: {total} queries, {bad} disagreements with blocked_reference, {dt:.1f} s "
          f"(dominated by the Python-integer reference)")
    return bad


def random_scene(rng, n):
    centres = rng.random((n, 1, 3)) * 10
    v = centres + (rng.random((n, 3, 3)) - 0.5) * 2
    return mesh_scene(v.reshape(-1, 3), np.arange(3 * n), name="bench")


def part_throughput(seed, patches=2000, blocks=300):
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, patches)
    samples = SampleScheme(8)
    board = ModelBoard(BoardParams(bits=16))
    board.prepare(scene, samples)

    # every patch in one voxel: the array streams all of them for every block
    board.load(SimpleNamespace(start=np.array([0]), count=np.array([patches]), patches=np.arange(patches)))
    blks = [BlockRay(np.full(8, i), np.arange(8), rng.choice(patches, 8, replace=False), np.array([0]))
            for i in rng.integers(0, patches, blocks)]
    t0 = time.perf_counter()
    board.run(blks)
    dt = time.perf_counter() - t0
    c = board.counters()
    print(f"throughput: {patches} patches, {blocks} blocks of 8 x 8, P = 8 boards, B = 16: "
          f"{c['tests_useful'] / dt / 1e6:.2f} M ray-patch tests/s "
          f"({c['tests_issued'] / dt / 1e6:.2f} M issued/s), {dt:.2f} s; "
          f"board_cycles {c['board_cycles']}, utilization {c['utilization']:.3f}")
    return c['tests_useful'] / dt


def _load_scene(name):
    from blockray.host_driver.scene.builtin import load_scene
    return load_scene(name)


def part_float(scene_name, seed, rays=20000, bits_range=range(10, 21)):
    """Per-ray disagreement of the model (quantised scene) with the golden board (float64 scene)."""
    from blockray.fixedpoint import quantise, choose_bits
    from blockray.host_driver.board.golden import GoldenBoard
    scene = _load_scene(scene_name)
    samples = SampleScheme(8)
    rng = np.random.default_rng(seed)
    N = scene.patches
    # only rays the render casts: pairs that can exchange light (formfactor.exchange_mask), which
    # excludes coplanar pairs (a ray between two patches of one flat wall has form factor 0)
    from blockray.host_driver.radiosity.formfactor import exchange_mask
    i = rng.integers(0, N, rays)
    k = rng.integers(0, samples.count, rays)
    j = np.empty_like(i)
    for shooter in np.unique(i):
        partners = np.flatnonzero(exchange_mask(scene, shooter))
        sel = i == shooter
        j[sel] = rng.choice(partners, sel.sum()) if len(partners) else shooter
    keep = i != j
    i, k, j = i[keep], k[keep], j[keep]
    gold = GoldenBoard()
    gold.prepare(scene, samples)
    allp = np.arange(N)
    g = np.array([gold.blocked_samples([a], [b], [c], allp)[0, 0]
                  for a, b, c in zip(i, k, j)])
    print(f"float: scene {scene_name} ({N} patches), {len(i)} random rays (exchanging pairs) against all patches, "
          f"golden blocked {g.mean():.2%}; choose_bits -> {choose_bits(scene, samples)[0]}")
    print("   B  max displacement / diagonal  disagreements  rate")
    rows = []
    for bits in bits_range:
        q = quantise(scene, samples, bits)
        P, Q = q.shooters[i, k], q.receivers[j]
        m = np.zeros(len(i), dtype=bool)
        for c in range(0, N, 256):
            V, n = q.vertices[c:c + 256], q.normals[c:c + 256]
            # one ray per (P, Q) pair: the diagonal of the block
            for s in range(0, len(i), 512):
                m[s:s + 512] |= _diag(P[s:s + 512], Q[s:s + 512], V, n)
        bad = int((m != g).sum())
        rows.append((bits, q.relative_error, bad, bad / len(i)))
        print(f"  {bits:2d}  {q.relative_error:26.2e}  {bad:13d}  {bad / len(i):.3%}")
    return rows


def _diag(P, Q, V, n):
    """blocked of ray m = (P[m], Q[m]) against patches V: (M,) bool, same arithmetic as blocked_block."""
    out = np.zeros(len(P), dtype=bool)
    for m in range(len(P)):
        out[m] = blocked_block(P[m:m + 1], Q[m:m + 1], V, n).any()
    return out


def part_render(scene_name, max_shots, bits_range=range(10, 21)):
    """Speed-versus-error table: renders with --board model at each B against --board golden."""
    from blockray.host_driver.render.render import render
    scene = _load_scene(scene_name)
    t0 = time.perf_counter()
    gold = render(scene, backend="golden", max_shots=max_shots)
    tg = time.perf_counter() - t0
    g = gold.radiosity
    print(f"render: {scene_name}, {scene.patches} patches, max_shots {max_shots}; golden {tg:.1f} s")
    print("   B  radiosity RMS rel error  max rel error  tests/s (board phase)  utilization")
    for bits in bits_range:
        t0 = time.perf_counter()
        r = render(scene, board=ModelBoard(BoardParams(bits=bits)), max_shots=max_shots)
        rep = r.report
        m = r.radiosity
        rms = float(np.sqrt(np.mean((m - g) ** 2)) / np.sqrt(np.mean(g ** 2)))
        mx = float(np.max(np.abs(m - g)) / np.max(np.abs(g)))
        rate = rep["tests"] / max(rep["seconds"]["board"], 1e-9)
        print(f"  {bits:2d}  {rms:23.2e}  {mx:13.2e}  {rate / 1e6:17.2f} M  {rep['utilization']:.3f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=["all", "exact", "throughput", "float", "render"], default="all")
    ap.add_argument("--queries", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--scene", default="cornell")
    ap.add_argument("--rays", type=int, default=20000)
    ap.add_argument("--max-shots", type=int, default=40)
    args = ap.parse_args(argv)
    print(f"machine: {platform.machine()} {platform.processor() or ''} python {platform.python_version()} "
          f"numpy {np.__version__}")
    bad = 0
    if args.part in ("all", "exact"):
        bad = part_exact(args.queries, args.seed)
    if args.part in ("all", "throughput"):
        part_throughput(args.seed)
    if args.part in ("all", "float"):
        part_float(args.scene, args.seed, rays=args.rays)
    if args.part == "render":
        part_render(args.scene, args.max_shots)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

"""Model vs golden on a full solve, split into its parts: where the solves stop, and which rays.

    python benchmarks/bench_room_ties.py matrix golden F_golden.npy --patches golden.csv
    python benchmarks/bench_room_ties.py matrix model F_model.npy --patches model.csv [--bits B]
    python benchmarks/bench_room_ties.py matrix golden F_moved.npy --move 0.1,0.2,0.3
    python benchmarks/bench_room_ties.py moved golden golden_moved.csv --move 0.1,0.2,0.3
    python benchmarks/bench_room_ties.py split F_golden.npy F_model.npy
    python benchmarks/bench_room_ties.py ties F_golden.npy F_model.npy [--bits B]
    python benchmarks/bench_room_ties.py near 361,1494 [--bits B]

``matrix``: ``render(SCENE, backend=BOARD, solver="jacobi", tolerance=1e-9)`` (the same as
``blockray render SCENE --board BOARD --solver jacobi --tolerance 1e-9``), saving the visible
form factors F[j, i] it gathered with (.npy) and the per-patch radiosity (``--patches``).
``--move dx,dy,dz`` renders the scene translated by that vector: the same scene with its float
coordinates rounded afresh. ``moved``: only the default render of the translated scene (no F).

``split``: from each board's F, the exact solution (``numpy.linalg.solve`` per channel) and
progressive refinement to 1e-3 (the render's default: the same shots, to the bit, as
``blockray render SCENE --board BOARD``), then the RMS of each against the other
(bench_formfactor.py ``change``'s measures): the solver stop of each board, and model vs golden
converged and at 1e-3.

``ties``: every (shooter, receiver) pair whose F differs between the boards is cast again, ray
by ray, on both boards and on the golden board with the scene's vertices jittered by +-1e-7
(``--seeds`` seeds). A ray whose golden answer flips under that jitter is a *tie*: on the float
scene it passes within 1e-7 of an occluder's edge or starts on its plane (a sample point on a
contact line). Then the model's bits are put back on the tie rays only, and on the other rays
only, and each F is solved exactly against golden's: the RMS each part carries.

``near``: every ray of the pairs into the given receivers on both boards (no F needed); of the
rays that differ, how many flip on golden under jitters of 1e-7 .. 1e-3 (scene units): ties flip
at 1e-7, near misses only at the scale of the model's quantisation.
"""

import argparse
import dataclasses

import numpy as np

from _run_header import print_run_header
from bench_formfactor import change_stats

from blockray.params import BoardParams
from blockray.samples import SampleScheme
from blockray.host_driver.radiosity import formfactor, ray_weights, solver as solvers
from blockray.host_driver.board.backends import make_board
from blockray.board import BlockBits
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.render.output import write_patches_csv
from blockray.host_driver.render.render import render
from blockray.host_driver.traverse.visibility import Visibility, _clear_bits
from blockray.host_driver.traverse.voxel import VoxelGrid
from blockray.host_driver.traverse.cost import default_voxels

SAMPLES = SampleScheme(8)


def _fmt(name, stats):
    return (f"{name}: RMS {stats['rms']:.3e} (R {stats['R']['rms']:.3e}, G {stats['G']['rms']:.3e}, "
            f"B {stats['B']['rms']:.3e}); max per patch {max(stats[c]['max'] for c in 'RGB'):.1%}, "
            f"p99 {max(stats[c]['p99'] for c in 'RGB'):.2%}")


def exact_solution(scene, F):
    """B = (I - rho F)^-1 E, per channel."""
    I = np.eye(len(F))
    return np.stack([np.linalg.solve(I - scene.reflectance[:, c:c + 1] * F, scene.emission[:, c])
                     for c in range(3)], axis=1)


def _moved(scene, move):
    """``scene`` translated by ``move`` ("dx,dy,dz"): its float coordinates rounded afresh."""
    if not move:
        return scene
    return dataclasses.replace(scene, vertices=scene.vertices + np.array([float(x) for x in move.split(",")]))


def moved(args):
    """``blockray render SCENE --board BOARD --patches CSV`` (progressive refinement to 1e-3) on the
    scene translated by ``--move``."""
    scene = _moved(load_scene(args.scene), args.move)
    write_patches_csv(args.patches, scene, render(scene, backend=args.board, bits=args.bits).radiosity)


def matrix(args):
    scene = _moved(load_scene(args.scene), args.move)
    r = render(scene, backend=args.board, bits=args.bits, solver="jacobi", tolerance=1e-9)
    np.save(args.out, r.factors)
    if args.patches:
        write_patches_csv(args.patches, scene, r.radiosity)
    print(f"{args.board}: {r.report['iterations']} sweeps, residual {r.report['residual']:.2e}, "
          f"{r.report['rays']} rays, {r.report['seconds']['total']:.0f} s")


def split(args):
    scene = load_scene(args.scene)
    exact, stop = {}, {}
    for name, path in (("golden", args.golden), ("model", args.model)):
        F = np.load(path)
        exact[name] = exact_solution(scene, F)
        p = solvers.progressive_refinement(scene, lambda i, F=F: F[:, i], tolerance=1e-3)
        stop[name] = p.B
        print(f"{name}: progressive to 1e-3: {p.shots} shots; exact solution's residual "
              f"{solvers.residual(scene, F, exact[name]):.1e}")
        print(_fmt(f"  {name} at 1e-3 vs {name} converged (solver stop)", change_stats(p.B, exact[name])))
    print(_fmt("model vs golden, converged", change_stats(exact["model"], exact["golden"])))
    print(_fmt("model vs golden, both at 1e-3", change_stats(stop["model"], stop["golden"])))


def _visibility(scene, board, bits=None):
    params = BoardParams()
    b = make_board(board, params.with_(bits=bits))
    b.prepare(scene, SAMPLES)
    grid = VoxelGrid(scene.patch_vertices, default_voxels(scene.patches, parallelism=1), margin=b.margin)
    b.load(grid)
    return Visibility(scene, b, grid, SAMPLES, rows=params.rows, cols=params.cols)


def ray_bits(vis, shooters, targets):
    """(n, K) 1.0 where the ray from sample k of shooters[m] to the centroid of targets[m] is clear."""
    batch, row_pair = vis._pair_blocks(shooters, targets)
    bits = vis.board.run(batch)
    flat = bits.flat if isinstance(bits, BlockBits) else np.concatenate(
        [np.asarray(b, dtype=bool).ravel() for b in bits])
    return _clear_bits(batch.row_off, batch.col_off, batch.shooter_sample, row_pair, flat, len(targets),
                       SAMPLES.count)


def flips(scene, shooters, targets, bits, amplitude, seeds):
    """(n, K) bool: rays whose golden answer ``bits`` flips with the scene's vertices jittered by
    +-``amplitude`` (uniform, seeds 1 .. ``seeds``), in any of those seeds."""
    out = np.zeros(bits.shape, dtype=bool)
    for seed in range(1, seeds + 1):
        rng = np.random.default_rng(seed)
        jittered = dataclasses.replace(scene, vertices=scene.vertices + rng.uniform(-amplitude, amplitude,
                                                                                     scene.vertices.shape))
        out |= ray_bits(_visibility(jittered, "golden"), shooters, targets) != bits
    return out


def _pairs_into(scene, receivers):
    """The rays the render casts for every pair that exchanges light with ``receivers``: (shooter,
    receiver, the patch whose samples start the rays, the patch whose centroid ends them)."""
    I, J = [], []
    for i in range(scene.patches):
        mask = formfactor.exchange_mask(scene, i)
        for j in receivers:
            if mask[j]:
                I.append(i)
                J.append(j)
    I, J = np.array(I, dtype=np.int64), np.array(J, dtype=np.int64)
    return (I, J, *_ray_ends(scene, I, J))


def _ray_ends(scene, I, J):
    """For pairs (I[m] shooter, J[m] receiver), the patches whose samples start the render's rays
    and whose centroid ends them: i's samples to j's centroid, or the reverse rays."""
    direct = np.array([ray_weights.centroid_in_front(scene, i, np.array([j]))[0] for i, j in zip(I, J)], dtype=bool)
    return np.where(direct, I, J), np.where(direct, J, I)


def near(args):
    """Every ray into ``receivers`` on both boards; of the rays that differ, how many golden flips
    under vertex jitters of growing size: ties flip at 1e-7, near misses at the quantisation's scale."""
    scene = load_scene(args.scene)
    receivers = [int(r) for r in args.receivers.split(",")]
    I, J, S, T = _pairs_into(scene, receivers)
    bg = ray_bits(_visibility(scene, "golden"), S, T)
    bm = ray_bits(_visibility(scene, "model", args.bits), S, T)
    differ = bg != bm
    counts = [int((differ & flips(scene, S, T, bg, a, args.seeds)).sum()) for a in (1e-7, 1e-6, 1e-5, 1e-4, 1e-3)]
    print(f"receivers {receivers}, model B = {args.bits or 'default'}: {len(I)} pairs, {differ.sum()} of "
          f"{differ.size} rays differ; of them flipping on golden under 1e-7 / 1e-6 / 1e-5 / 1e-4 / 1e-3 m "
          f"jitter ({args.seeds} seeds): {' / '.join(map(str, counts))}")
    for m in np.flatnonzero(differ.any(axis=1)):
        print(f"  {scene.group_names[scene.group[I[m]]]} {I[m]} -> {J[m]}: golden clear {bg[m].astype(int)}, "
              f"model clear {bm[m].astype(int)}")


def ties(args):
    scene = load_scene(args.scene)
    Fg, Fm = np.load(args.golden), np.load(args.model)
    J, I = np.nonzero(Fg != Fm)
    if len(J) == 0:
        print("the boards' F are identical: no ray differs")
        return
    S, T = _ray_ends(scene, I, J)
    W = ray_weights.pair_sample_weights(scene, SAMPLES, S, T)

    def fraction(bits):
        total = W.sum(axis=1)
        return np.where(total > 0, (bits * W).sum(axis=1) / np.where(total > 0, total, 1), bits.mean(axis=1))
    bg = ray_bits(_visibility(scene, "golden"), S, T)
    bm = ray_bits(_visibility(scene, "model", args.bits), S, T)
    unoccluded = np.where(fraction(bg) > 0, Fg[J, I] / np.maximum(fraction(bg), 1e-300),
                          Fm[J, I] / np.maximum(fraction(bm), 1e-300))
    assert np.allclose(unoccluded * fraction(bm), Fm[J, I], rtol=1e-12, atol=0), "F_model is not this board's"
    tie = flips(scene, S, T, bg, 1e-7, args.seeds)
    differ = bg != bm
    print(f"{len(J)} entries of F differ ({len(np.unique(I))} shooters); {differ.sum()} of their "
          f"{differ.size} rays differ, {(differ & tie).sum()} of them ties "
          f"(golden flips under a 1e-7 jitter, {args.seeds} seeds): golden blocked / model clear "
          f"{(differ & tie & (bg == 0)).sum()}, the other way {(differ & tie & (bg == 1)).sum()}")
    Bg = exact_solution(scene, Fg)
    for name, bits in (("model's bits on the tie rays only", np.where(tie, bm, bg)),
                       ("model's bits on the other rays only", np.where(tie, bg, bm))):
        F = Fg.copy()
        F[J, I] = unoccluded * fraction(bits)
        print(_fmt(f"{name} vs golden, converged", change_stats(exact_solution(scene, F), Bg)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="room")
    sub = ap.add_subparsers(dest="what", required=True)
    m = sub.add_parser("matrix")
    m.add_argument("board")
    m.add_argument("out", help="F as .npy")
    m.add_argument("--bits", type=int, default=None)
    m.add_argument("--patches", default=None)
    m.add_argument("--move", default=None, help="dx,dy,dz: translate the scene first")
    mv = sub.add_parser("moved")
    mv.add_argument("board")
    mv.add_argument("patches", help="--patches CSV of the moved scene's render")
    mv.add_argument("--move", required=True, help="dx,dy,dz")
    mv.add_argument("--bits", type=int, default=None)
    for name in ("split", "ties"):
        p = sub.add_parser(name)
        p.add_argument("golden", help="golden board's F (.npy, from matrix)")
        p.add_argument("model", help="model board's F (.npy, from matrix)")
    sub.choices["ties"].add_argument("--bits", type=int, default=None, help="the model's B (as in matrix)")
    sub.choices["ties"].add_argument("--seeds", type=int, default=3)
    n = sub.add_parser("near")
    n.add_argument("receivers", help="patch numbers, comma-separated")
    n.add_argument("--bits", type=int, default=None, help="the model's B (default: the scene's)")
    n.add_argument("--seeds", type=int, default=4)
    args = ap.parse_args(argv)
    print_run_header()
    {"matrix": matrix, "moved": moved, "split": split, "ties": ties, "near": near}[args.what](args)


if __name__ == "__main__":
    main()

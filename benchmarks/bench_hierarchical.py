"""Error against speed: --solver hierarchical against the uniform progressive solve.

    python benchmarks/bench_hierarchical.py cornell --reference-edge 70 --check-edge 100 \
        --uniform-edges 300,200,100 --epsilons 1e-2,3e-3,1e-3,3e-4,1e-4 --link-rays spread --clustering on,off \
        --plot docs/img/hierarchical-cornell.png

The reference is a uniform Jacobi solve on the golden board (``--reference-edge``,
``--reference-samples``, tolerance 1e-6), kept in ``--cache`` between runs; its distance to a coarser uniform solve of the
same kind (``--check-edge``) is printed as the reference's own refinement error. Each run's error
is the area-weighted L1 distance on the reference mesh, per channel (the largest of the three
printed), relative to the reference's area-weighted mean: every reference patch takes the
radiosity of the run's patch or leaf that holds its centroid. Rays, board cycles and CPU seconds (the
process's, every thread) are the render's report. The hierarchical runs start from the input triangles
(``--max-edge`` 1e9) or from the scene subdivided to each ``--hierarchical-edges``; the uniform
runs from the scene subdivided to each edge length.

After the table it prints each hierarchical run against the uniform solve at the same error: the
uniform rays, board cycles and CPU seconds interpolated as a power law between the two uniform
runs (in order of rays) whose errors bracket the run's (:func:`at_equal_error`), over the
hierarchical run's; runs outside the uniform errors are marked so, not extrapolated.
"""

import argparse
import os
import time

import numpy as np

from _run_header import print_run_header
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.render.render import render

RAW = 1e9          # no subdivision: the input triangles


def locate(tri, points, chunk=256):
    """Index of the triangle of ``tri`` (T, 3, 3) holding each point (M, 3): of the triangles whose
    plane passes within 1e-7 of the scene's size, the one the point is deepest inside."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    n2 = (n * n).sum(axis=1)
    size = np.ptp(tri.reshape(-1, 3), axis=0).max()
    out = np.empty(len(points), dtype=np.int64)
    for s in range(0, len(points), chunk):
        p = points[s:s + chunk, None, :]
        off = ((p - a) * n).sum(axis=-1) / np.sqrt(n2)
        w = [((np.cross(v1 - v0, p - v0)) * n).sum(axis=-1) / n2 for v0, v1 in ((b, c), (c, a), (a, b))]
        inside = np.minimum(np.minimum(w[0], w[1]), w[2])
        inside = np.where(np.abs(off) < 1e-7 * size, inside, -np.inf)
        out[s:s + chunk] = np.argmax(inside, axis=1)
    return out


def error(reference, result):
    """Largest per-channel area-weighted L1 distance on the reference mesh, relative."""
    ref = reference["scene"]
    at = locate(result.scene.patch_vertices, ref.centroids)
    A = ref.areas[:, None]
    diff = (A * np.abs(result.radiosity[at] - reference["B"])).sum(axis=0)
    return float((diff / (A * reference["B"]).sum(axis=0)).max())


def reference_solution(name, edge, cache, samples, board="golden"):
    tag = "" if board == "golden" else f"-{board}"
    path = os.path.join(cache, f"hier-ref-{name}-{edge:g}-{samples}{tag}.npz")
    scene = load_scene(name, max_edge=edge)
    if os.path.exists(path):
        B = np.load(path)["B"]
        if B.shape == (scene.patches, 3):
            return {"scene": scene, "B": B, "seconds": float(np.load(path)["seconds"])}
    t0 = time.process_time()
    result = render(scene, backend=board, solver="jacobi", samples=samples, tolerance=1e-6)
    seconds = time.process_time() - t0
    os.makedirs(cache, exist_ok=True)
    np.savez(path, B=result.radiosity, seconds=seconds)
    return {"scene": scene, "B": result.radiosity, "seconds": seconds}


def run(reference, name, edge, **options):
    scene = load_scene(name, max_edge=edge)
    result = render(scene, backend="model", **options)
    r = result.report
    return {"patches": scene.patches, "rays": r["rays"], "cycles": r["board_cycles"], "cpu": r["cpu_seconds"]["total"],
            "error": error(reference, result), "leaves": r.get("leaves", scene.patches),
            "links": r["links"] + r["cluster_links"] if "cluster_links" in r else r.get("links", ""),
            "balance": max((b for b in r.get("absorbed_balance") or [] if b is not None), key=abs, default=float("nan"))}


def warm_up():
    """Render a small scene once with each solver, so numba's compilation (cached on disk after a
    first run, recompiled when a kernel's module changes) falls in no measured run."""
    scene = load_scene("cornell", max_edge=RAW)
    render(scene, backend="model", solver="progressive", tolerance=1e-2)
    for clustering in (True, False):
        render(scene, backend="model", solver="hierarchical", epsilon=1e-2, clustering=clustering)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--reference-edge", type=float, default=70.0)
    ap.add_argument("--reference-samples", type=int, default=8)
    ap.add_argument("--check-edge", type=float, default=100.0)
    ap.add_argument("--reference-board", default="golden", choices=["golden", "model"],
                    help="the reference's board (model: for scenes too large for the golden board)")
    ap.add_argument("--uniform-edges", default="300,200,100")
    ap.add_argument("--epsilons", default="1e-2,3e-3,1e-3,3e-4,1e-4")
    ap.add_argument("--hierarchical-edges", default=f"{RAW:g}",
                    help="the hierarchical runs' input meshes, each in turn (comma-separated max edges; "
                         f"{RAW:g}: the input triangles)")
    ap.add_argument("--link-rays", default="spread",
                    help="the hierarchical runs' --link-rays, each in turn (comma-separated)")
    ap.add_argument("--clustering", default="on",
                    help="the hierarchical runs' --clustering, each in turn (comma-separated on/off)")
    ap.add_argument("--tolerance", type=float, default=1e-3)
    ap.add_argument("--cache", default=os.environ.get("TMPDIR", "/tmp"))
    ap.add_argument("--plot", metavar="PNG", help="write error against rays and CPU seconds")
    args = ap.parse_args(argv)
    print_run_header()
    print(f"# load average before: {os.getloadavg()}", flush=True)
    warm_up()
    ref = reference_solution(args.scene, args.reference_edge, args.cache, args.reference_samples, args.reference_board)
    check = reference_solution(args.scene, args.check_edge, args.cache, args.reference_samples, args.reference_board)
    fake = type("R", (), {"scene": check["scene"], "radiosity": check["B"]})
    print(f"# reference: {ref['scene'].patches} patches, {args.reference_board}, jacobi 1e-6, {args.reference_samples} samples, {ref['seconds']:.0f} CPU s; "
          f"the same at max edge {args.check_edge:g} ({check['scene'].patches} patches) is {error(ref, fake):.4f} "
          f"from it", flush=True)
    print("| solver | mesh | patches / leaves | links | rays | board cycles | CPU s | error | balance |")
    print("|---|---|---|---|---|---|---|---|---|")
    modes = args.link_rays.split(",")
    starts = [float(x) for x in args.hierarchical_edges.split(",")]
    modes = [(m, c == "on") for c in args.clustering.split(",") for m in modes]
    label = lambda mode, edge: (f"hierarchical, {mode[0]}" + ("" if mode[1] else ", no clustering")
                                + ("" if edge == RAW else f", from max edge {edge:g}"))
    rows = {"progressive": [], **{label(m, e): [] for e in starts for m in modes}}
    for edge in (float(x) for x in args.uniform_edges.split(",")):
        r = run(ref, args.scene, edge, solver="progressive", tolerance=args.tolerance)
        rows["progressive"].append(dict(r, mesh=f"max edge {edge:g}"))
        print(f"| progressive | max edge {edge:g} | {r['patches']} | | {r['rays']} | {r['cycles']} | {r['cpu']:.2f} | "
              f"{r['error']:.4f} | "
              f"{r['balance']:+.2%} |", flush=True)
    for edge in starts:
        for mode in modes:
            for eps in (float(x) for x in args.epsilons.split(",")):
                r = run(ref, args.scene, edge, solver="hierarchical", epsilon=eps, tolerance=args.tolerance / 10,
                        link_rays=mode[0], clustering=mode[1])
                rows[label(mode, edge)].append(dict(r, mesh=f"epsilon {eps:g}"))
                print(f"| {label(mode, edge)} | epsilon {eps:g} | {r['leaves']} | {r['links']} | {r['rays']} | "
                      f"{r['cycles']} | {r['cpu']:.2f} | {r['error']:.4f} | {r['balance']:+.2%} |", flush=True)
    print(f"# load average after: {os.getloadavg()}")
    print_equal_error(rows)
    if args.plot:
        plot(rows, args.plot, args.scene)


def at_equal_error(uniform, error, key):
    """``uniform``'s ``key`` (rays, cycles, cpu) at ``error``: the power law through the two runs,
    neighbours in order of rays, whose errors bracket ``error`` (the first such pair); None when
    no pair does."""
    runs = sorted(uniform, key=lambda r: r["rays"])
    for a, b in zip(runs, runs[1:]):
        if min(a["error"], b["error"]) <= error <= max(a["error"], b["error"]) and a["error"] != b["error"]:
            t = np.log(error / a["error"]) / np.log(b["error"] / a["error"])
            return float(a[key] * (b[key] / a[key]) ** t)
    return None


def print_equal_error(rows):
    """Each hierarchical run against the uniform solve at its error (:func:`at_equal_error`)."""
    print("| solver | mesh | error | rays: uniform / hierarchical | board cycles | CPU s |")
    print("|---|---|---|---|---|---|")
    for solver, runs in rows.items():
        for r in runs if solver != "progressive" else ():
            cells = []
            for key, fmt in (("rays", "{:.3g}"), ("cycles", "{:.3g}"), ("cpu", "{:.3g} s")):
                u = at_equal_error(rows["progressive"], r["error"], key)
                cells.append("outside the uniform errors" if u is None else
                             f"{fmt.format(u)} / {fmt.format(r[key])} = **{u / r[key]:.1f}x**")
            print(f"| {solver} | {r['mesh']} | {r['error']:.4f} | " + " | ".join(cells) + " |")


def plot(rows, path, name):
    """Error against rays, board cycles (the machine's time) and CPU seconds, one line per solver."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, key, label in zip(axes, ("rays", "cycles", "cpu"), ("rays", "board cycles", "CPU seconds")):
        for (solver, runs), marker in zip(rows.items(), ("o-", "s-", "^-", "v-", "D-", "x-")):
            ax.loglog([r[key] for r in runs], [r["error"] for r in runs], marker, label=solver)
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())     # decade labels only
        ax.set_xlabel(label)
        ax.set_ylabel("relative L1 error")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend()
    fig.suptitle(f"{name}: error against the reference, hierarchical vs uniform progressive")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    main()

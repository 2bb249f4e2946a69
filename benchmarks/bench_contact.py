"""Energy balance of closed scenes with and without contact-line splitting (host_driver/scene/contact.py).

    python benchmarks/bench_contact.py room cornell-closed --board model --tolerance 1e-4

Prints one markdown row per scene and setting: patches, what the split did, the solve, and
absorbed / emitted - 1 per channel (host_driver/radiosity/closure.py's absorbed_balance). ``--row-sums``
instead solves by Jacobi (every column of visible factors) and prints, per group, the area-weighted
mean of each patch's visible row sum sum_i F_ji minus 1 (0 in a closed scene), and its extremes. ``cornell-closed`` is
the built-in cornell file with a front wall over its opening (its floor as published, running under
the blocks), loaded as a user's OBJ file would be, at the built-in's subdivision.
"""

import argparse
import shutil
import tempfile
import time
from pathlib import Path

from blockray.host_driver.scene.builtin import DEFAULT_MAX_EDGE, load_scene, path
from blockray.host_driver.radiosity.closure import absorbed_balance
from blockray.host_driver.render.render import render

#: The opening at z = 0: the floor's and the ceiling's front corners (the red wall is slanted, so
#: it is not the bounding box's face), counter-clockwise from inside the box: it faces +z, inwards.
FRONT_WALL = """
o front_wall
usemtl white
v 0 0 0
v 552.8 0 0
v 556 548.8 0
v 0 548.8 0
f -4 -3 -2 -1
"""


def closed_cornell_file(folder):
    obj = Path(folder) / "cornell_closed.obj"
    shutil.copy(path("cornell").with_suffix(".mtl"), Path(folder) / "cornell.mtl")
    obj.write_text(path("cornell").read_text() + FRONT_WALL)
    return obj


def load(name, folder, contact):
    if name == "cornell-closed":
        return load_scene(str(closed_cornell_file(folder)), max_edge=DEFAULT_MAX_EDGE["cornell"], contact=contact)
    return load_scene(name, contact=contact)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs="+", choices=["room", "cornell-closed"])
    p.add_argument("--board", default="model")
    p.add_argument("--tolerance", type=float, default=1e-4)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--row-sums", action="store_true")
    args = p.parse_args()
    if args.row_sums:
        return row_sums(args)
    print("| scene | contact | patches | split / covered whole / pieces dropped | shots | residual "
          "| absorbed / emitted - 1 (R, G, B) | seconds |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as folder:
        for name in args.scenes:
            for contact in (False, True):
                scene = load(name, folder, contact)
                t = time.perf_counter()
                res = render(scene, backend=args.board, tolerance=args.tolerance, threads=args.threads)
                c = scene.contact
                did = f"{c['patches_split']} / {c['patches_covered']} / {c['covered_pieces']}" if c else "-"
                print(f"| {name} | {'on' if contact else 'off'} | {scene.patches} | {did} | {res.report['shots']} "
                      f"| {res.report['residual']:.1e} | "
                      + ", ".join(f"{x:+.3%}" for x in absorbed_balance(scene, res.radiosity))
                      + f" | {time.perf_counter() - t:.0f} |", flush=True)


def row_sums(args):
    print("| scene | contact | group | patches | area | area-weighted mean (row sum - 1) | min | max |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as folder:
        for name in args.scenes:
            for contact in (False, True):
                scene = load(name, folder, contact)
                res = render(scene, backend=args.board, solver="jacobi", tolerance=1e-6, threads=args.threads)
                rows, A = res.factors.sum(axis=1), scene.areas
                for g in ["all"] + list(range(len(scene.group_names))):
                    m = scene.group == g if g != "all" else slice(None)
                    if not A[m].size:
                        continue
                    print(f"| {name} | {'on' if contact else 'off'} | {scene.group_names[g] if g != 'all' else 'all'} "
                          f"| {A[m].size} | {A[m].sum():.3f} | {(A[m] * (rows[m] - 1)).sum() / A[m].sum():+.4f} "
                          f"| {rows[m].min():.3f} | {rows[m].max():.3f} |", flush=True)


if __name__ == "__main__":
    main()

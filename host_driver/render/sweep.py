"""Speed against error: one scene rendered over a grid of settings, each point's cost and its error
against a reference render (``blockray sweep``; docs/speed-vs-error.md).

Every point is an ordinary ``blockray render`` in a process of its own, so a point is exactly what
a user gets from the same command line (the CSV records it), and one point's failure or memory
does not touch the others. A point's files live in ``OUT/points/<id>/``; a point whose report and
patches are already there is not rendered again (a sweep resumes where it stopped).

Error against the reference, per channel c, on the reference's mesh (areas A_i, radiosity r_i):

    rms_c = sqrt(sum_i A_i (b_i - r_i)^2 / sum_i A_i r_i^2)
    max_c = max_i |b_i - r_i| / sqrt(sum_i A_i r_i^2 / sum_i A_i)

where b_i is the point's radiosity at the reference patch i's centroid: the radiosity of the point's
patch (same group) that holds that centroid. On the same mesh that is patch i itself.
"""

import csv
import json
import math
import os
import re
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass, field
from itertools import product

import numpy as np

from ...atomic import Outputs
from ...cell import CELLS
from ...errors import ParameterError, option, printable
from ...params import MAX_BITS, MIN_BITS
from ...samples import END_LATTICES
from ..traverse.endpoints import ENDS
from ..traverse.visibility import PACKINGS
from .options import ESTIMATORS, LINK_RAYS, SAMPLE_POINTS, SOLVERS

__all__ = ["SETTINGS", "RECIPES", "Setting", "parse_vary", "points", "Reference", "read_patches",
           "error_against", "map_to_mesh", "leaf_triangles", "pareto_front", "plot_front", "run_sweep", "COLUMNS"]


@dataclass(frozen=True)
class Setting:
    """A render option a sweep may vary: its flag, the type of its values and, if closed, its choices."""
    flag: str
    kind: type
    choices: tuple = ()
    check: object = None        # value -> error text or None


def _positive(v):
    return None if v > 0 and math.isfinite(v) else "must be positive and finite"


def _bits(v):
    return None if MIN_BITS <= v <= MAX_BITS else f"must be from {MIN_BITS} to {MAX_BITS}"


def _board_choices():
    from ..board.backends import BACKENDS
    return tuple(n for n in BACKENDS if n != "ulx3s")     # a sweep does not drive real hardware


#: name -> Setting; every render option that changes cost or error
SETTINGS = {
    "bits": Setting("--bits", int, check=_bits),
    "samples": Setting("--samples", int, check=_positive),
    "voxels": Setting("--voxels", int, check=_positive),
    "tolerance": Setting("--tolerance", float, check=_positive),
    "max-edge": Setting("--max-edge", float, check=_positive),
    "solver": Setting("--solver", str, SOLVERS),
    "epsilon": Setting("--epsilon", float, check=_positive),      # hierarchical refinement threshold
    "min-area": Setting("--min-area", float, check=_positive),    # hierarchical smallest element
    "link-rays": Setting("--link-rays", str, LINK_RAYS),           # hierarchical link visibility
    "clustering": Setting("--clustering", str, ("on", "off")),     # hierarchical initial links
    "board": Setting("--board", str, None),                # choices from the registry, when asked
    "cell": Setting("--cell", str, CELLS),
    "traversal": Setting("--traversal", str, ("block", "ray")),
    "packing": Setting("--packing", str, PACKINGS),
    "estimator": Setting("--estimator", str, tuple(ESTIMATORS)),
    "end-points": Setting("--end-points", str, ENDS),
    "end-seed": Setting("--end-seed", int, check=lambda v: None if v >= 0 else "must not be negative"),
    "end-draws": Setting("--end-draws", int, check=_positive),
    "emitter-factor": Setting("--emitter-factor", int, check=_positive),
    "end-lattice": Setting("--end-lattice", int, END_LATTICES),
    "sample-points": Setting("--sample-points", str, SAMPLE_POINTS),
    "sample-seed": Setting("--sample-seed", int, check=lambda v: None if v >= 0 else "must not be negative"),
    "contact": Setting("--contact", str, ("on", "off")),
    "rows": Setting("--rows", int, check=_positive),
    "cols": Setting("--cols", int, check=_positive),
    "boards": Setting("--boards", int, check=_positive),
    "max-shots": Setting("--max-shots", int, check=_positive),
}

#: named references: the render options of each (``max-edge: "half"`` halves the scene's edge)
RECIPES = {
    "golden": {"board": "golden", "samples": 32, "tolerance": 1e-5},
    "golden-fine": {"board": "golden", "samples": 32, "tolerance": 1e-5, "max-edge": "half"},
    # the model board is within 1e-4 of golden (docs/formfactors.md) and about 10x faster: for scenes
    # whose golden reference costs hours, when the points' errors are far above 1e-4
    "model": {"board": "model", "samples": 32, "tolerance": 1e-5},
}


def _value(name, text, option="--vary"):
    s = SETTINGS[name]
    try:
        v = s.kind(text)
    except ValueError:
        raise ParameterError(f"{option} {name}: {text!r} is not {'an integer' if s.kind is int else 'a number'}") \
            from None
    choices = _board_choices() if name == "board" else s.choices
    if choices and v not in choices:
        raise ParameterError(f"{option} {name}: {text!r} is not one of {', '.join(choices)}")
    why = s.check(v) if s.check else None
    if why:
        raise ParameterError(f"{option} {name}: {text} {why}")
    return v


def parse_vary(specs, option="--vary"):
    """``["bits=12,14", "samples=4,8"]`` -> ``{"bits": [12, 14], "samples": [4, 8]}`` (in order)."""
    grid = {}
    for spec in specs:
        name, eq, values = spec.partition("=")
        name = name.strip().replace("_", "-")
        if not eq or not values.strip():
            raise ParameterError(f"{option} {spec!r}: expected NAME=V1,V2,... (e.g. bits=12,14,16)")
        if name not in SETTINGS:
            raise ParameterError(f"{option} {name}: not a setting a sweep can vary (one of {', '.join(SETTINGS)})")
        if name in grid:
            raise ParameterError(f"{option} {name}: given twice")
        vals = [_value(name, t.strip(), option) for t in values.split(",") if t.strip()]
        if len(set(vals)) != len(vals):
            raise ParameterError(f"{option} {name}: a value is repeated")
        grid[name] = vals
    if not grid:
        raise ParameterError(f"{option}: give at least one setting to vary, e.g. --vary samples=4,8,16")
    return grid


def points(grid):
    """Every combination of the grid, as ``{name: value}`` in the grid's order."""
    names = list(grid)
    return [dict(zip(names, combo)) for combo in product(*(grid[n] for n in names))]


def point_id(settings):
    """A folder name for a point: ``bits-12_samples-4``."""
    return "_".join(f"{n}-{v:g}" if isinstance(v, float) else f"{n}-{v}" for n, v in settings.items())


def render_args(scene, settings):
    """The ``blockray render`` arguments of a point (its outputs excluded)."""
    args = [scene]
    for name, v in settings.items():
        args += [SETTINGS[name].flag, repr(v) if isinstance(v, float) else str(v)]
    return args


# ---------------------------------------------------------------------------- error on a mesh

def read_patches(path):
    """A ``--patches`` CSV -> (groups (N,) str, areas (N,), centroids (N, 3), radiosity (N, 3),
    leaves): ``leaves`` is each row's (input triangle, level) for a hierarchical CSV, else None."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
        groups = np.array([r["group"] for r in rows])
        num = np.array([[float(r[k]) for k in ("area", "cx", "cy", "cz", "B_r", "B_g", "B_b")] for r in rows])
        leaves = None
        if rows and "level" in rows[0]:
            leaves = np.array([int(r["patch"]) for r in rows]), np.array([int(r["level"]) for r in rows])
    except (OSError, KeyError, ValueError, csv.Error) as e:
        raise ParameterError(f"{option('reference')} {printable(path, 200)}: not a blockray {option('patches')} CSV ({e})") from None
    if len(rows) == 0 or not np.isfinite(num).all():
        raise ParameterError(f"{option('reference')} {printable(path, 200)}: no patches, or a number that is not finite")
    return groups, num[:, 0], num[:, 1:4], num[:, 4:7], leaves


def map_to_mesh(centroids, groups, tri, tri_groups, candidates=16):
    """For each point ``centroids[i]``, the index of the triangle ``tri`` (M, 3, 3) of the same group
    that holds it: the least distance outside it, among the ``candidates`` triangles whose bounding
    spheres come nearest the point."""
    tc = tri.mean(axis=1)
    radius = np.linalg.norm(tri - tc[:, None, :], axis=2).max(axis=1)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    out = np.empty(len(centroids), dtype=np.int64)
    k = min(candidates, len(tri))
    for lo in range(0, len(centroids), 256):
        c, g = centroids[lo:lo + 256], groups[lo:lo + 256]
        d = np.sqrt(((c[:, None, :] - tc[None, :, :]) ** 2).sum(axis=2)) - radius[None, :]
        d[g[:, None] != tri_groups[None, :]] = np.inf
        near = np.argpartition(d, k - 1, axis=1)[:, :k]                    # (m, k)
        out[lo:lo + 256] = near[np.arange(len(c)), _outside(c, tri[near], n[near]).argmin(axis=1)]
    return out


def _outside(p, t, n):
    """How far each point p (m, 3) lies outside each candidate triangle t (m, k, 3, 3): its distance
    from the plane plus its distance outside the edges, both in scene units."""
    p = p[:, None, :]
    nn = np.linalg.norm(n, axis=2)
    plane = np.abs(((p - t[:, :, 0]) * n).sum(axis=2)) / nn
    off = np.zeros(plane.shape)
    for a in range(3):
        e, q = t[:, :, (a + 1) % 3] - t[:, :, a], p - t[:, :, a]
        inward = np.cross(n, e)                                            # points into the triangle
        off += np.maximum(0.0, -(q * inward).sum(axis=2) / np.linalg.norm(inward, axis=2))
    return plane + off


def error_against(ref_areas, ref, value):
    """Per-channel area-weighted RMS and maximum errors of ``value`` against ``ref`` (module doc)."""
    a = ref_areas[:, None]
    scale = np.sqrt((a * ref ** 2).sum(axis=0))
    with np.errstate(divide="ignore", invalid="ignore"):
        rms = np.sqrt((a * (value - ref) ** 2).sum(axis=0)) / scale
        mx = np.abs(value - ref).max(axis=0) / (scale / math.sqrt(ref_areas.sum()))
    return np.nan_to_num(rms, nan=0.0), np.nan_to_num(mx, nan=0.0)


# ---------------------------------------------------------------------------- the front

def pareto_front(cost, error):
    """Indices of the points no other point beats in both cost and error, by increasing cost."""
    order = sorted(range(len(cost)), key=lambda i: (cost[i], error[i]))
    front, best = [], math.inf
    for i in order:
        if error[i] < best:
            front.append(i)
            best = error[i]
    return front


# ---------------------------------------------------------------------------- running

#: the columns of sweep.csv, after one per varied setting
COLUMNS = ["status", "error_rms", "error_rms_r", "error_rms_g", "error_rms_b", "error_max", "error_max_r",
           "error_max_g", "error_max_b", "cpu_s", "wall_s", "process_wall_s", "rays", "tests", "board_cycles",
           "board_s", "embree_s", "patches", "bits", "command"]


@dataclass
class Reference:
    """The reference a sweep measures against: its patches CSV, how it was made, and its mesh."""
    csv: str
    recipe: dict = field(default_factory=dict)      # the render settings, or {} for a given CSV
    command: str = ""

    def load(self):
        self.groups, self.areas, self.centroids, self.radiosity, _ = read_patches(self.csv)
        return self


def _blockray():
    return [sys.executable, "-m", "blockray"]


def _run_render(scene, settings, folder, echo):
    """Render one point into ``folder``: (report dict, process wall seconds) or raise ParameterError
    with the render's own one-line error."""
    os.makedirs(folder, exist_ok=True)
    report, patches = os.path.join(folder, "report.json"), os.path.join(folder, "patches.csv")
    if os.path.exists(report) and os.path.exists(patches):
        with open(report) as f:
            return json.load(f), None
    args = ["render", *render_args(scene, settings), "--patches", patches + ".part", "--report",
            report + ".part", "--quiet"]
    t0 = time.perf_counter()
    proc = subprocess.run(_blockray() + args, capture_output=True, text=True, stdin=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        lines = [l for l in proc.stderr.splitlines() if l.strip()]
        raise ParameterError((lines[-1] if lines else f"exit status {proc.returncode}").removeprefix("blockray: "))
    with open(report + ".part") as f:
        rep = json.load(f)
    rep["process_wall_s"] = wall
    with open(report + ".part", "w") as f:
        json.dump(rep, f, indent=2)
    os.replace(patches + ".part", patches)      # patches first: a report means the point is whole
    os.replace(report + ".part", report)
    echo(f"rendered {printable(folder, 120)} in {wall:.1f} s")
    return rep, wall


def _half_edge(scene, fixed):
    from ..scene.builtin import DEFAULT_MAX_EDGE, load_scene
    if "max-edge" in fixed:
        return fixed["max-edge"] / 2
    if scene in DEFAULT_MAX_EDGE:
        return DEFAULT_MAX_EDGE[scene] / 2
    pv = load_scene(scene).patch_vertices
    return float(np.linalg.norm(pv - np.roll(pv, 1, axis=1), axis=2).max()) / 2


def make_reference(scene, spec, fixed, out, echo):
    """``spec``: a recipe name (rendered into ``out/reference``, once) or a patches CSV."""
    if spec not in RECIPES:
        if not os.path.isfile(spec):
            raise ParameterError(f"{option('reference')} {printable(spec, 200)}: neither a recipe ({', '.join(RECIPES)}) "
                                 f"nor a patches CSV file")
        return Reference(spec).load()
    recipe = {**fixed, **RECIPES[spec]}
    if recipe.get("max-edge") == "half":
        recipe["max-edge"] = _half_edge(scene, fixed)
    folder = os.path.join(out, "reference")
    try:
        _run_render(scene, recipe, folder, echo)
    except ParameterError as e:
        raise ParameterError(f"{option('reference')} {spec}: the reference render failed: {e.spelled(option)}") from None
    return Reference(os.path.join(folder, "patches.csv"), recipe,
                     " ".join(["blockray", "render", *render_args(scene, recipe)])).load()


class _Meshes:
    """The point's radiosity on the reference's mesh (module doc), loading each point mesh once."""

    def __init__(self, scene, ref):
        self.scene, self.ref, self.maps = scene, ref, {}

    def on_reference(self, settings, csv_path):
        groups, _, centroids, value, leaves = read_patches(csv_path)
        ref = self.ref
        if len(groups) == len(ref.groups) and np.array_equal(centroids, ref.centroids):
            return value
        key = (settings.get("max-edge"), settings.get("contact", "on"))
        if leaves is not None:          # hierarchical: each point has its own leaves, so no cache
            patch, level = leaves
            tri = leaf_triangles(self._mesh(key).patch_vertices[patch], level, centroids)
            return value[map_to_mesh(ref.centroids, ref.groups, tri, groups)]
        if key not in self.maps:
            mesh = self._mesh(key)
            if mesh.patches != len(groups):
                raise ParameterError(f"{csv_path}: {len(groups)} patches, but the scene loads as {mesh.patches}")
            names = np.array(mesh.group_names)[mesh.group] if mesh.group_names else mesh.group.astype(str)
            self.maps[key] = map_to_mesh(ref.centroids, ref.groups, mesh.patch_vertices, names)
        return value[self.maps[key]]

    def _mesh(self, key):
        from ..scene.builtin import load_scene
        return load_scene(self.scene, max_edge=key[0], contact=key[1] == "on")


def leaf_triangles(inputs, level, centroids, chunk=4096):
    """Each leaf's triangle (N, 3, 3): of the elements of its ``level`` below its input triangle
    ``inputs`` (N, 3, 3), the one whose centroid is the leaf's (the nearest, in barycentric terms)."""
    from ..radiosity.elements import level_corners
    a, e1, e2 = inputs[:, 0], inputs[:, 1] - inputs[:, 0], inputs[:, 2] - inputs[:, 0]
    q = centroids - a
    g11, g12, g22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    det = g11 * g22 - g12 ** 2
    v = ((q * e1).sum(1) * g22 - (q * e2).sum(1) * g12) / det
    w = ((q * e2).sum(1) * g11 - (q * e1).sum(1) * g12) / det
    bary = np.stack([1 - v - w, v, w], axis=1)
    out = np.empty(inputs.shape)
    for lv in np.unique(level):
        corners = level_corners(int(lv))                                   # (E, 3, 3) barycentric
        centre = corners.mean(axis=1)
        for m in np.array_split(np.flatnonzero(level == lv), max(1, (level == lv).sum() // chunk)):
            pick = ((bary[m, None, :] - centre[None]) ** 2).sum(axis=2).argmin(axis=1)
            out[m] = np.einsum("nvk,nkd->nvd", corners[pick], inputs[m])
    return out


def embree_seconds_per_ray(scene, rays=200_000, seed=1):
    """CPU seconds per occlusion ray of Embree (embreex) on ``scene``: segments from random points of
    random patches to random patches' centroids, ``rays`` of them; None without embreex."""
    try:
        from ..traverse.peer import embree_occluded
    except ImportError:
        return None
    rng = np.random.default_rng(seed)
    pv = scene.patch_vertices
    i, j = rng.integers(0, len(pv), rays), rng.integers(0, len(pv), rays)
    w = rng.dirichlet(np.ones(3), rays)
    P = (w[:, :, None] * pv[i]).sum(axis=1)
    Q = scene.centroids[j]
    _, _, cpu, _ = embree_occluded(scene, P, Q)
    return cpu / rays


def _row(settings, rep, err, fmax, embree):
    rms, mx = err
    cycles = rep.get("board_cycles")
    cpu = rep["cpu_seconds"]["total"]
    return {**settings, "status": "ok", "error_rms": float(rms.max()), **{f"error_rms_{c}": float(v) for c, v in zip("rgb", rms)},
            "error_max": float(mx.max()), **{f"error_max_{c}": float(v) for c, v in zip("rgb", mx)},
            "cpu_s": cpu, "wall_s": rep["seconds"]["total"], "process_wall_s": rep.get("process_wall_s"),
            "rays": rep["rays"], "tests": rep["tests"], "board_cycles": cycles,
            "board_s": None if cycles is None else cycles / (fmax * 1e6),
            "embree_s": None if embree is None else rep["rays"] * embree,
            "patches": rep.get("leaves", rep["patches"]), "bits": rep.get("bits")}


def run_sweep(scene, grid, *, reference="golden", fixed=None, out="sweep", fmax=50.0, progress=False,
              echo=lambda text: None):
    """Render every point of ``grid`` (see :func:`parse_vary`) with the ``fixed`` settings, measure
    each against ``reference``; writes ``out/sweep.csv``, ``out/sweep.json`` and, with matplotlib,
    ``out/pareto.png``, all three together (blockray/atomic.py). Returns the rows (failed points carry
    ``status`` = their error)."""
    from tqdm import tqdm
    from ..scene.builtin import load_scene
    fixed = dict(fixed or {})
    if set(fixed) & set(grid):
        raise ParameterError(f"{option('fix')} {', '.join(sorted(set(fixed) & set(grid)))}: also given to {option('vary')}")
    os.makedirs(out, exist_ok=True)
    ref = make_reference(scene, reference, fixed, out, echo)
    embree = embree_seconds_per_ray(load_scene(scene, max_edge=fixed.get("max-edge")))
    meshes = _Meshes(scene, ref)
    rows = []
    for settings in tqdm(points(grid), desc="sweep", unit="point", disable=not progress):
        every = {**fixed, **settings}
        folder = os.path.join(out, "points", point_id(settings))
        command = " ".join(["blockray", "render", *render_args(scene, every)])
        try:
            rep, _ = _run_render(scene, every, folder, echo)
            value = meshes.on_reference(every, os.path.join(folder, "patches.csv"))
            rows.append({**_row(settings, rep, error_against(ref.areas, ref.radiosity, value), fmax, embree),
                         "command": command})
        except ParameterError as e:
            rows.append({**settings, "status": f"failed: {e}", "command": command})
    command = sweep_command(scene, grid, fixed, reference, fmax)
    with Outputs() as outputs:
        _write(outputs, out, scene, grid, fixed, ref, fmax, embree, rows, command)
        plotted = plot_front(outputs, rows, grid, os.path.join(out, "pareto.png"),
                             f"{os.path.basename(scene)}: RMS error against CPU time", command)
    if not plotted:
        echo("no plot: matplotlib is not installed (pip install 'blockray[plot]'); the tables are written")
    return rows


def sweep_command(scene, grid, fixed, reference, fmax):
    """The ``blockray sweep`` command line of these settings (printed on the plot, kept in the JSON)."""
    vary = [f"--vary {n}={','.join(f'{v:g}' if isinstance(v, float) else str(v) for v in vs)}" for n, vs in grid.items()]
    fix = [f"--fix {n}={v:g}" if isinstance(v, float) else f"--fix {n}={v}" for n, v in fixed.items()]
    fm = [] if fmax == 50.0 else [f"--fmax {fmax:g}"]
    return " ".join(["blockray", "sweep", shlex.quote(scene), *vary, *fix, "--reference", shlex.quote(reference), *fm])


def _write(outputs, out, scene, grid, fixed, ref, fmax, embree, rows, command):
    names = list(grid)

    def table(f):
        w = csv.DictWriter(f, fieldnames=names + COLUMNS, restval="")
        w.writeheader()
        w.writerows({k: ("" if v is None else v) for k, v in r.items()} for r in rows)

    meta = {"command": command, "scene": scene, "vary": grid, "fixed": fixed, "reference": {"csv": ref.csv, "recipe": ref.recipe,
            "command": ref.command}, "fmax_mhz": fmax, "embree_cpu_s_per_ray": embree,
            "error": "per channel: area-weighted RMS relative to the reference's, and max |b - r| relative to its "
                     "area-weighted RMS radiosity, on the reference's mesh; error_rms/error_max: worst channel",
            "points": rows}
    outputs.add(os.path.join(out, "sweep.csv"), "--out", table)
    outputs.add(os.path.join(out, "sweep.json"), "--out", lambda f: json.dump(meta, f, indent=2))


def plot_front(outputs, rows, grid, path, title, command):
    """Error against CPU seconds, log-log, each point labelled by its setting and the front drawn,
    the ``command`` that made it below, staged in ``outputs``. Returns False when matplotlib is not
    installed."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib import ticker
    except ImportError:
        return False
    ok = [r for r in rows if r.get("status") == "ok" and r["error_rms"] > 0]
    fig, ax = plt.subplots(figsize=(8, 6))
    ax.scatter([r["cpu_s"] for r in ok], [r["error_rms"] for r in ok], s=18, color="tab:blue")
    for r in ok:
        ax.annotate(" ".join(f"{n}={r[n]:g}" if isinstance(r[n], float) else f"{n}={r[n]}" for n in grid),
                    (r["cpu_s"], r["error_rms"]), fontsize=6, xytext=(3, 3), textcoords="offset points")
    front = [ok[i] for i in pareto_front([r["cpu_s"] for r in ok], [r["error_rms"] for r in ok])]
    ax.step([r["cpu_s"] for r in front], [r["error_rms"] for r in front], where="post", color="tab:red",
            label="Pareto front")
    ax.set(xscale="log", yscale="log", xlabel="CPU seconds of the render",
           ylabel="RMS error against the reference (worst channel)", title=title)
    plain = ticker.FuncFormatter(lambda v, _: f"{v:g}")   # 20, 50, 100 s, not 2 x 10^1
    ax.xaxis.set_major_locator(ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(plain)
    ax.xaxis.set_minor_formatter(ticker.NullFormatter())
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.text(0.01, 0.005, command, fontsize=6, family="monospace", va="bottom")
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    try:
        outputs.add(path, "--out", lambda f: fig.savefig(f, format="png", dpi=120), binary=True)
    finally:
        plt.close(fig)
    return True

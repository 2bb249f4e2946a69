"""The render loop: scene -> board -> form factors -> solver -> outputs.

This is the host of the paper's machine: it voxelises, walks block rays through the grid, sends
them to a board (any :class:`~blockray.board.Board` back-end), turns the blocked bits
into visible form factors and solves for radiosity.

Visibility of a (shooter i, receiver j) pair is the fraction of the rays from i's sample points to
j's centroid that the board reports clear, each ray weighted by the light its sample sends to j
(:func:`~blockray.host_driver.radiosity.ray_weights.sample_weights`: 0 from samples behind j's plane); for a
receiver whose centroid lies behind i's plane, the reverse rays (from j's samples to i's centroid);
the form factor is the exact patch-to-patch factor ``F_ji``
(:func:`~blockray.host_driver.radiosity.formfactor.unoccluded_factors`) times that fraction. Rays are cast
only for pairs that can exchange light (:func:`~blockray.host_driver.radiosity.formfactor.exchange_mask`).
"""

import time
from dataclasses import dataclass, field

import numpy as np

from ...atomic import Outputs
from ...errors import ParameterError, option
from ..board.backends import build_board, make_board
from .options import SOLVERS, RenderOptions, estimator_of
from ... import threads as host_threads
from ..radiosity import closure as closures, formfactor, solver as solvers
from ..cluster.scaleout import check_sets, combine_counters, exchange_bytes_per_sweep
from ..traverse.endpoints import EndPoints
from ..traverse.visibility import TRAVERSALS, Phases, Visibility, _morton, visible_fraction
from ..traverse.voxel import VoxelGrid
from ..traverse.board_walk import board_grid
from ..traverse.cost import TraversalStats, default_voxels

__all__ = ["RenderResult", "RenderOptions", "make_board", "Visibility", "render", "SOLVERS", "TRAVERSALS"]


@dataclass
class RenderResult:
    scene: object
    radiosity: np.ndarray
    solve: object
    report: dict = field(default_factory=dict)
    factors: object = None        # (N, N) visible form factors F[j, i], when a gathering solver built them


def render(scene, board=None, options=None, *, progress=False, echo=None, checkpoint=None, **flat):
    """Solve the radiosity of ``scene`` with every visibility query answered by ``board``.

    ``options``: a :class:`~blockray.host_driver.render.options.RenderOptions` (or its flat names as
    keywords, :meth:`~blockray.host_driver.render.options.RenderOptions.of`). ``board``: a built
    :class:`~blockray.board.Board`; None: the registry (host_driver/board/backends.py) builds
    ``options.board`` and the board is closed at the end. ``progress``: show a progress bar;
    ``echo(text)`` is told the cluster's dashboard address.

    ``options.run``: ``sets`` > 1, a ``scheduler`` address or a number of ``workers`` run the
    render as ``sets`` host + board sets on a Dask cluster (host_driver/cluster/cluster.py): the user's
    at ``scheduler``, else a LocalCluster of ``workers`` processes (default one per core, at most
    ``sets``); each set builds its own ``options.board``. ``threads``: cores the compiled host
    kernels use (None: all, see :mod:`blockray.threads`); the result does not depend on it.

    ``options.solve.closure``: ``"symmetric"`` or ``"enforce"`` build every column first and make
    the visible factors reciprocal (and, ``"enforce"``, closed: for closed scenes only), see
    host_driver/radiosity/closure.py; the report's ``closure`` key then gives the errors before and after,
    the size of the correction, and the energy balance solved with the raw and the corrected
    factors side by side.

    ``checkpoint``: a :class:`~blockray.host_driver.render.checkpoint.Checkpoint` that saves the solve
    as it runs and/or gives the state it continues from (not with ``closure``).

    Returns a :class:`RenderResult` whose ``report`` holds the keys of ``--report``.
    """
    if options is None:
        options = RenderOptions.of(**flat)
    elif flat:
        raise TypeError("render() takes options or their flat names, not both")
    with host_threads.using(options.run.threads):
        if board is not None:
            return _render(scene, board, options, progress=progress, echo=echo, checkpoint=checkpoint)
        # the waveforms (--vcd) are renamed into place when the board is closed after a render
        with Outputs() as outputs, build_board(options.board, outputs) as board:     # closed on every path
            return _render(scene, board, options, progress=progress, echo=echo, checkpoint=checkpoint)


def _resume(scene, board, options, params, checkpoint):
    """The state ``checkpoint`` continues from (None: from the beginning), bound to the scene and
    the options it was saved with."""
    if checkpoint is None:
        return None
    b, ray, solve = options.board, options.ray, options.solve
    hierarchical = {"epsilon": solve.epsilon, "min_area": solve.min_area, "closure": solve.closure,
                    "link_rays": solve.link_rays, "clustering": solve.clustering} \
        if solve.solver == "hierarchical" else {}
    if solve.closure != "off" and not hierarchical:
        raise ParameterError(f"{option('checkpoint')} / {option('resume')}: a {option('closure')} render solves twice "
                             "from the whole matrix; "
                             "it is not checkpointed", parameter="closure")
    return checkpoint.bind(scene, {
        "board": board.name, "bits": b.params.bits, "voxels": ray.voxels, "samples": ray.samples.count,
        "solver": solve.solver, "tolerance": solve.tolerance, "max_shots": solve.max_shots,
        "max_iterations": solve.max_iterations, "traversal": ray.traversal, "packing": options.packing,
        "end_points": ray.end_points, "end_seed": ray.end_seed, "end_draws": ray.end_draws,
        "emitter_factor": ray.emitter_factor,
        "end_lattice": ray.end_lattice, "sample_points": ray.sample_points, "sample_seed": ray.sample_seed,
        "partition": b.partition, "sets": options.run.sets, "cell": b.cell.kind, "filter_format": repr(b.cell.format),
        "rows": params.rows, "cols": params.cols, "boards": params.boards, **hierarchical})


def _render(scene, board, options, *, progress, echo, checkpoint):
    if options.solve.solver == "hierarchical":
        return _hierarchical(scene, board, options, checkpoint)
    b, ray, solve = options.board, options.ray, options.solve
    params = getattr(board, "params", None) or b.params       # R, S, P of the board as built
    if options.run.distributed:
        if board.name != b.backend:
            raise ParameterError(f"{option('sets')}: every set builds a {b.backend!r} board (options.board), not the "
                                 f"{board.name!r} given", parameter="sets")
        check_sets(options.run.sets, scene.patches)
    samples = ray.samples
    resume = _resume(scene, board, options, params, checkpoint)
    phases = Phases()
    t_start, c_start = time.perf_counter(), time.process_time()

    with phases.timed("prepare"):
        board.prepare(scene, samples)
    # The paper's cost model (5)-(8) sizes the grid. With the hardware's P x R x S parallelism the
    # test term nearly vanishes and it asks for a very coarse grid; the boards here run in
    # software at about one test per 0.05-0.2 us, so the default is the model's optimum for one
    # processor. The hardware optimum is reported alongside.
    voxels_hardware = default_voxels(scene.patches, parallelism=params.processors * params.boards)
    voxels = ray.voxels or default_voxels(scene.patches, parallelism=1)
    with phases.timed("voxelise"):
        grid = (board_grid(board, voxels) if ray.traversal == "board"           # the board makes the rays
                else VoxelGrid(scene.patch_vertices, voxels, margin=board.margin))
    run = _Run(scene=scene, board=board, options=options, params=params, phases=phases, t_start=t_start,
               voxels=voxels, voxels_hardware=voxels_hardware, checkpoint=checkpoint, resume=resume)
    if options.run.distributed:
        return _render_sets(run, grid, progress=progress, echo=echo)
    with phases.timed("load"):
        board.load(grid)

    stats = TraversalStats(grid, sample_fraction=ray.stats_fraction)
    vis = Visibility(scene, board, grid, samples, rows=params.rows, cols=params.cols,
                     traversal=ray.traversal, packing=options.packing, phases=phases, stats=stats,
                     ends=EndPoints(scene, samples, ray.end_points, ray.end_seed, ray.end_draws,
                                    ray.emitter_factor))
    # A patch may shoot more than once; its column of visible form factors does not change.
    cache = {} if scene.patches <= 20000 else None
    if checkpoint is not None and cache is not None:
        checkpoint.columns = cache.keys
    pair_cache = formfactor.PairCache(scene)      # each unordered pair's factor computed once

    def shoot(i):
        if cache is not None and i in cache:
            return cache[i].astype(np.float64)
        with phases.timed("formfactor"):
            # exact patch-to-patch factors; the exchange mask is applied inside
            f_all = formfactor.unoccluded_factors(scene, i, cache=pair_cache)
            solvers.check_factors(i, f_all, "exact factor")    # a NaN would pass "f > 0" as 0
            receivers = np.flatnonzero(f_all > 0)
            f = f_all[receivers]
        frac = visible_fraction(scene, vis, samples, i, receivers, phases)
        out = np.zeros(scene.patches)
        out[receivers] = f * frac
        if cache is not None:
            cache[i] = out.astype(np.float32) if scene.patches > 4000 else out
        return out

    bar = _progress(progress, solve.solver,
                    scene.patches if solve.solver != "progressive" or solve.closure != "off" else solve.max_shots)
    saving = None if checkpoint is None else checkpoint.save
    closure_info = factors = None
    with phases.timed("solve"):
        if solve.closure != "off":
            result, closure_info = _solve_closed(scene, shoot, solve, bar)
        elif solve.solver == "progressive":
            result = solvers.progressive_refinement(scene, shoot, tolerance=solve.tolerance,
                                                    max_shots=solve.max_shots, progress=bar, refuse_gain=True,
                                                    checkpoint=saving, resume=resume)
        else:
            factors, sums = _columns(scene, shoot, bar)
            result = _solve_matrix(scene, factors, solve, checkpoint=saving, resume=resume)
            result.row_sums = sums
    solvers.check_finite(scene, result)         # nothing non-finite is written
    if bar is not None:
        bar.close()
    inner = ("formfactor", "commands", "traverse", "board")
    for times in (phases.seconds, phases.cpu):
        for phase in inner:
            times.setdefault(phase, 0.0)
        # time inside shoot() is also inside "solve": report the solver's own arithmetic separately
        times["solve"] -= sum(times[p] for p in inner)
    seconds = dict(phases.seconds)
    seconds["total"] = time.perf_counter() - t_start
    cpu_seconds = dict(phases.cpu)
    cpu_seconds["total"] = time.process_time() - c_start

    report = _report(run, board.name, result=result, rays=vis.rays, blocks=vis.blocks, columns=vis.columns,
                     counters=board.counters(), seconds=seconds, cpu_seconds=cpu_seconds,
                     traversal_stats=stats.summary())
    report["exchange_bytes_per_sweep"] = 0
    if closure_info is not None:
        report["closure"] = closure_info
    _resumed(report, resume)
    return RenderResult(scene=scene, radiosity=result.B, solve=result, report=report, factors=factors)


def _hierarchical(scene, board, options, checkpoint):
    """``--solver hierarchical`` (host_driver/render/hierarchical.py): the result's scene is the leaf
    elements', ``hierarchy`` the elements and links."""
    from .hierarchical import render_hierarchical
    params = getattr(board, "params", None) or options.board.params
    resume = _resume(scene, board, options, params, checkpoint)
    saving = None if checkpoint is None else checkpoint.save
    if options.run.distributed:
        from ..cluster.cluster import cluster_client
        check_sets(options.run.sets, scene.patches)
        sets = options.run
        with cluster_client(sets.scheduler, workers=sets.workers, sets=sets.sets) as cluster:
            h = render_hierarchical(scene, board, options, checkpoint=saving, resume=resume, cluster=cluster)
        h.report["sets"] = int(sets.sets)
    else:
        h = render_hierarchical(scene, board, options, checkpoint=saving, resume=resume)
    if resume is not None:
        h.report["resumed_from"] = {"shots": 0, "sweeps": int(resume["iterations"]), "rounds": int(resume["rounds"])}
    result = RenderResult(scene=h.leaves, radiosity=h.radiosity, solve=h, report=h.report)
    result.hierarchy = h
    return result


def _solve_closed(scene, shoot, solve, bar):
    """Every column of visible factors, made reciprocal / closed (host_driver/radiosity/closure.py), then
    solved twice with ``solve.solver``: with the corrected factors (the result) and with the raw
    ones, so that the report shows both energy balances side by side."""
    mode = solve.closure
    if 8 * scene.patches ** 2 > solvers.MAX_MATRIX_BYTES:
        raise ParameterError(f"{option('closure')} {mode}: the form factors of {scene.patches} patches do not fit in "
                             f"{solvers.MAX_MATRIX_BYTES / 2**30:g} GiB", parameter="closure")
    F, sums = _columns(scene, shoot, bar)
    t0 = time.perf_counter()
    corrected, info = closures.enforce(scene, F, mode=mode)
    info["enforce_seconds"] = time.perf_counter() - t0
    result = _solve_matrix(scene, corrected, solve)
    raw = _solve_matrix(scene, F, solve)
    result.row_sums = sums                      # of the raw factors: the report's visible_row_sum
    info["absorbed_balance"] = closures.absorbed_balance(scene, result.B).tolist()
    info["absorbed_balance_raw"] = closures.absorbed_balance(scene, raw.B).tolist()
    info["residual_raw"] = float(raw.residual)
    parts = closures.imbalance_terms(scene, F, raw.B)
    info["raw_imbalance_from_closure"], info["raw_imbalance_from_reciprocity"] = (p.tolist() for p in parts)
    return result, info


def _columns(scene, shoot, bar):
    """``(F, row_sums)``: the dense visible factors ``F[j, i]``, one shooter's column at a time,
    each checked as it comes (:class:`~blockray.host_driver.radiosity.solver.RowSums`)."""
    F = np.zeros((scene.patches, scene.patches))
    sums = solvers.RowSums(refuse_gain=True)
    for i in range(scene.patches):
        F[:, i] = shoot(i)
        sums.check(scene, i, F[:, i])
        if bar is not None:
            bar.update(1)
    return F, sums


def _solve_matrix(scene, F, solve, *, checkpoint=None, resume=None):
    if solve.solver == "progressive":
        return solvers.progressive_refinement(scene, lambda i: F[:, i], tolerance=solve.tolerance,
                                              max_shots=solve.max_shots, refuse_gain=True)
    gather = solvers.jacobi if solve.solver == "jacobi" else solvers.gauss_seidel
    return gather(scene, F, tolerance=solve.tolerance, max_iterations=solve.max_iterations, checkpoint=checkpoint,
                  resume=resume)


def _resumed(report, resume):
    """The report's ``resumed_from``: the shots or sweeps the checkpoint had done (absent when
    the render started from the beginning)."""
    if resume is not None:
        report["resumed_from"] = {"shots": int(resume["shots"]), "sweeps": int(resume["iterations"])}


@dataclass(frozen=True)
class _Run:
    """What a render's report says of the run besides its results."""
    scene: object
    board: object
    options: object
    params: object
    phases: object
    t_start: float
    voxels: int
    voxels_hardware: int
    checkpoint: object = None
    resume: object = None


def _ends_label(ray):
    """The report's end-point rule: its name, with the draw's seed, rows per pair and lattice."""
    extra = [f"seed {ray.end_seed}"] if ray.end_points == "draw" else []
    extra += [f"{ray.end_draws} draws"] if ray.end_draws > 1 else []
    extra += [f"{ray.emitter_factor}x from emitters"] if ray.emitter_factor > 1 else []
    extra += [f"lattice 1/{ray.samples.denominator}"] if ray.end_lattice > 1 else []
    return ray.end_points + (f" ({', '.join(extra)})" if extra else "")


def _report(run, board_name, *, result, rays, blocks, columns, counters, seconds, traversal_stats, cpu_seconds=None):
    """The keys of ``--report`` (the board's own counters last, never overriding the host's)."""
    scene, params, ray, solve = run.scene, run.params, run.options.ray, run.options.solve
    report = {
        "scene": scene.name,
        "source": scene.source,
        "patches": int(scene.patches),
        "contact": scene.contact,        # patches split along contact lines at load (None: not done)
        "voxels": int(run.voxels),
        "voxels_hardware_optimum": int(run.voxels_hardware),
        "columns_cast": int(columns),
        "board": board_name,
        "board_params": {"rows": params.rows, "cols": params.cols, "boards": params.boards},
        "samples": ray.samples.count,
        "traversal": ray.traversal,
        "packing": run.options.packing,
        "estimator": estimator_of(ray),
        "end_points": _ends_label(ray),
        "sample_points": ray.sample_points + (f" (seed {ray.sample_seed})" if ray.samples.drawn else ""),
        "partition": getattr(run.board, "partition", None),
        "solver": solve.solver,
        "sets": int(run.options.run.sets),
        "tolerance": solve.tolerance,
        "shots": int(getattr(result, "shots", 0) or 0),
        "iterations": int(getattr(result, "iterations", 0) or 0),
        "rays": int(rays),
        "blocks": int(blocks),
        "tests": int(counters.get("tests", 0)),
        "tests_per_ray": float(counters.get("tests", 0)) / max(1, rays),
        "residual": float(result.residual),
        "visible_row_sum": result.row_sums.summary() if result.row_sums is not None else None,
        "absorbed_balance": _absorbed_balance(scene, result.B),
        "balance_by_group": result.row_sums.balance_by_group(scene, result.B) if result.row_sums is not None else None,
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
        "host_seconds_per_ray": sum(seconds.get(p, 0.0) for p in ("commands", "traverse", "board")) / max(1, rays),
        "traversal_stats": traversal_stats,
        "threads": host_threads.get(),
    }
    for key, value in counters.items():
        report.setdefault(key, value)
    return report


def _absorbed_balance(scene, B):
    """absorbed / emitted power - 1 per channel (closure.absorbed_balance); None for a channel
    that nothing emits. Of a progressive state, the light still unshot counts as not absorbed."""
    with np.errstate(divide="ignore", invalid="ignore"):
        balance = closures.absorbed_balance(scene, B)
    return [float(b) if np.isfinite(b) else None for b in balance]


def _render_sets(run, grid, *, progress, echo):
    """render()'s gathering on host + board sets of a Dask cluster (host_driver/cluster/cluster.py), from
    the client's prepared (not loaded) board and voxel grid. Every set builds its own board of
    ``options.board`` with the B the client's board quantised the scene to."""
    from ..cluster.cluster import SetJob, cluster_client, solve_sets
    scene, options, phases, params = run.scene, run.options, run.phases, run.params
    b, ray, solve, sets = options.board, options.ray, options.solve, options.run
    quantised = getattr(run.board, "quantised", None)       # None: a board that does not quantise
    with phases.timed("cluster"), cluster_client(sets.scheduler, workers=sets.workers, sets=sets.sets,
                                                 echo=echo) as (client, threads):
        job = SetJob(board=b.backend, params=params if quantised is None else params.with_(bits=quantised.bits),
                     partition=b.partition, samples=ray.samples, traversal=ray.traversal, packing=options.packing,
                     stats_fraction=ray.stats_fraction, threads=threads, end_points=ray.end_points,
                     end_seed=ray.end_seed, end_draws=ray.end_draws, emitter_factor=ray.emitter_factor)
        owner, result, summaries, info = solve_sets(client, scene, grid, sets.sets,
                                                    _morton(grid.cell_of(scene.centroids)), job,
                                                    solver=solve.solver, tolerance=solve.tolerance,
                                                    max_iterations=solve.max_iterations, progress=progress,
                                                    checkpoint=None if run.checkpoint is None else run.checkpoint.save,
                                                    resume=run.resume)
    solvers.check_finite(scene, result)
    phases.add("cluster", -(info["assign_seconds"] + info["cast_seconds"] + info["solve_seconds"]))
    phases.add("assign", info["assign_seconds"])
    phases.add("cast", info["cast_seconds"])
    phases.add("solve", info["solve_seconds"])
    for s in summaries:                       # the sets' own phases, summed over the sets
        for phase in ("prepare", "load", "formfactor", "traverse", "board"):
            phases.add(phase, s["phases"].get(phase, 0.0))
    seconds = dict(phases.seconds)
    seconds["total"] = time.perf_counter() - run.t_start
    stats = TraversalStats(grid)
    for s in summaries:
        stats.add_counts(s["stats"])
    counters = combine_counters(owner, summaries, params.processors * params.boards)
    report = _report(run, b.backend, result=result, rays=sum(s["rays"] for s in summaries),
                     blocks=sum(s["blocks"] for s in summaries), columns=max(s["columns"] for s in summaries),
                     counters=counters, seconds=seconds, traversal_stats=stats.summary())
    report["exchange_bytes_per_sweep"] = int(exchange_bytes_per_sweep(owner))
    report["cluster"] = {
        "scheduler": sets.scheduler or "LocalCluster",
        "workers": [{"address": a, "nthreads": w.get("nthreads")} for a, w in sorted(info["workers"].items())],
        "kernel_threads": threads,
        "exchanged_bytes": int(info["exchanged_bytes"]),
        "exchanges": int(info["exchanges"]),
        "cast_seconds_per_set": [float(s["seconds"]) for s in summaries],
        "cast_cpu_seconds_per_set": [float(s["cpu_seconds"]) for s in summaries],
    }
    _resumed(report, run.resume)
    return RenderResult(scene=scene, radiosity=result.B, solve=result, report=report)


def _progress(enabled, solver, total):
    if not enabled:
        return None
    from tqdm import tqdm
    unit = "shot" if solver == "progressive" else "column"
    return tqdm(total=total, unit=unit, desc=f"{solver}", leave=False)

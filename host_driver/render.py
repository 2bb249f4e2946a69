"""The render loop: scene -> board -> form factors -> solver -> outputs.

This is the host of the paper's machine: it voxelises, walks block rays through the grid, sends
them to a board (any :class:`~blockray.host_driver.board.Board` back-end), turns the blocked bits
into visible form factors and solves for radiosity.

Visibility of a (shooter i, receiver j) pair is the fraction of the rays from i's sample points to
j's centroid that the board reports clear, each ray weighted by the light its sample sends to j
(:func:`~blockray.host_driver.formfactor.sample_weights`: 0 from samples behind j's plane); for a
receiver whose centroid lies behind i's plane, the reverse rays (from j's samples to i's centroid);
the form factor is the exact patch-to-patch factor ``F_ji``
(:func:`~blockray.host_driver.formfactor.unoccluded_factors`) times that fraction. Rays are cast
only for pairs that can exchange light (:func:`~blockray.host_driver.formfactor.exchange_mask`).
"""

import time
from dataclasses import dataclass, field

import numpy as np

from ..params import BoardParams
from ..samples import SampleScheme
from ..errors import ParameterError
from .backends import backend, make_board
from .. import threads as host_threads
from . import closure as closures, formfactor, solver as solvers
from .scaleout import check_sets, combine_counters, exchange_bytes_per_sweep
from .visibility import PACKINGS, TRAVERSALS, Phases, Visibility, _morton, visible_fraction
from .voxel import VoxelGrid, default_voxels, TraversalStats

__all__ = ["RenderResult", "make_board", "Visibility", "render", "SOLVERS", "TRAVERSALS"]

SOLVERS = ("progressive", "jacobi", "gauss-seidel")


@dataclass
class RenderResult:
    scene: object
    radiosity: np.ndarray
    solve: object
    report: dict = field(default_factory=dict)
    factors: object = None        # (N, N) visible form factors F[j, i], when a gathering solver built them


def render(scene, *, board="golden", params=None, bits=None, voxels=None, samples=8,
           solver="progressive", tolerance=1e-3, max_shots=None, max_iterations=200,
           traversal="block", packing="voxel", partition="deal", sets=1, progress=False,
           stats_fraction=0.02, vcd=None, threads=None, scheduler=None, workers=None, echo=None, host=None,
           cell="exact", filter_format=None, closure="off", checkpoint=None):
    """Solve the radiosity of ``scene`` with every visibility query answered by ``board``.

    ``board``: a name of the back-end registry (host_driver/backends.py) or a Board; ``vcd``,
    ``host``, ``cell``, ``filter_format``: see :func:`~blockray.host_driver.backends.make_board`.

    ``threads``: cores the compiled host kernels use (None: all, see
    :mod:`blockray.threads`); the result does not depend on it.

    ``sets`` > 1, a ``scheduler`` address or a number of ``workers`` run the render as ``sets``
    host + board sets on a Dask cluster (host_driver/cluster.py): the user's at ``scheduler``,
    else a LocalCluster of ``workers`` processes (default one per core, at most ``sets``).
    ``echo(text)`` is told the cluster's dashboard address.

    ``closure``: ``"symmetric"`` or ``"enforce"`` build every column first and make the visible
    factors reciprocal (and, ``"enforce"``, closed: for closed scenes only), see
    host_driver/closure.py; the report's ``closure`` key then gives the errors before and after,
    the size of the correction, and the energy balance solved with the raw and the corrected
    factors side by side.

    ``checkpoint``: a :class:`~blockray.host_driver.checkpoint.Checkpoint` that saves the solve
    as it runs and/or gives the state it continues from (not with ``closure``).

    A board built here (``board`` a name) is closed on every path: success, error or signal.

    Returns a :class:`RenderResult` whose ``report`` holds the keys of ``--report``.
    """
    with host_threads.using(threads):
        return _render(scene, board=board, params=params, bits=bits, voxels=voxels, samples=samples,
                       solver=solver, tolerance=tolerance, max_shots=max_shots, max_iterations=max_iterations,
                       traversal=traversal, packing=packing, partition=partition, sets=sets,
                       progress=progress, stats_fraction=stats_fraction, vcd=vcd,
                       scheduler=scheduler, workers=workers, echo=echo, host=host, cell=cell,
                       filter_format=filter_format, closure=closure, checkpoint=checkpoint)


def _render(scene, *, board, params, bits, voxels, samples, solver, tolerance, max_shots, max_iterations,
            traversal, packing, partition, sets, progress, stats_fraction, vcd, scheduler, workers, echo, host,
            cell, filter_format, closure, checkpoint):
    if solver not in SOLVERS:
        raise ParameterError(f"--solver must be one of {', '.join(SOLVERS)}, not {solver!r}")
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise ParameterError(f"--tolerance must be a positive number, not {tolerance!r}")
    if max_shots is not None and max_shots < 1:
        raise ParameterError(f"--max-shots must be at least 1, not {max_shots!r}")
    if closure not in closures.MODES:
        raise ParameterError(f"--closure must be one of {', '.join(closures.MODES)}, not {closure!r}")
    params = params or BoardParams()
    distributed = sets != 1 or scheduler is not None or workers is not None
    if distributed and closure != "off":
        raise ParameterError("--closure needs the whole form-factor matrix on one host; it cannot be used with "
                             "--sets, --scheduler or --workers", parameter="closure")
    if distributed:
        if solver == "progressive":
            raise ParameterError("--sets: host + board sets solve by gathering; use --solver jacobi or "
                                 "gauss-seidel", parameter="sets")
        if not isinstance(board, str):
            raise ParameterError("--sets needs a board name (one board is built per set)", parameter="sets")
        if vcd is not None:
            raise ParameterError("--vcd traces one board's simulation; it cannot be used with --sets, "
                                 "--scheduler or --workers", parameter="vcd")
        if host is not None:
            raise ParameterError("--link-idle / --link-backpressure / --link-bursts drive one simulated board; "
                                 "they cannot be used with --sets, --scheduler or --workers", parameter="sets")
        if cell != "exact":
            raise ParameterError("--cell filtered runs one set (not with --sets, --scheduler or --workers)",
                                 parameter="cell")
        if scheduler is not None and workers is not None:
            raise ParameterError("--workers sizes the local cluster; a cluster joined with --scheduler has its own "
                                 "workers", parameter="workers")
        check_sets(sets, scene.patches)
    if bits is not None and isinstance(board, str) and not backend(board).quantises:
        raise ParameterError("--bits applies to boards that quantise the scene; the golden board is float64")
    samples = samples if isinstance(samples, SampleScheme) else SampleScheme(samples)
    resume = None
    if checkpoint is not None:
        if closure != "off":
            raise ParameterError("--checkpoint / --resume: a --closure render solves twice from the whole matrix; "
                                 "it is not checkpointed", parameter="closure")
        resume = checkpoint.bind(scene, {
            "board": board if isinstance(board, str) else board.name, "bits": bits, "voxels": voxels,
            "samples": samples.count, "solver": solver, "tolerance": tolerance, "max_shots": max_shots,
            "max_iterations": max_iterations, "traversal": traversal, "packing": packing, "partition": partition,
            "sets": sets, "cell": cell, "filter_format": repr(filter_format), "rows": params.rows,
            "cols": params.cols, "boards": params.boards})
    phases = Phases()
    t_start, c_start = time.perf_counter(), time.process_time()
    board_obj = (make_board(board, params, bits=bits, vcd=vcd, partition=partition, host=host, cell=cell,
                            filter_format=filter_format)
                 if isinstance(board, str) else board)
    board_name = board if isinstance(board, str) else board_obj.name
    try:
        return _render_on(scene, board, board_obj, board_name, params, samples, phases, t_start, c_start,
                          voxels=voxels, solver=solver, tolerance=tolerance, max_shots=max_shots,
                          max_iterations=max_iterations, traversal=traversal, packing=packing,
                          partition=partition, sets=sets, progress=progress, stats_fraction=stats_fraction,
                          scheduler=scheduler, workers=workers, echo=echo, closure=closure,
                          distributed=distributed, checkpoint=checkpoint, resume=resume)
    finally:
        if isinstance(board, str) and hasattr(board_obj, "close"):
            board_obj.close()                   # a simulated board stops its simulator


def _render_on(scene, board, board_obj, board_name, params, samples, phases, t_start, c_start, *, voxels, solver,
               tolerance, max_shots, max_iterations, traversal, packing, partition, sets, progress, stats_fraction,
               scheduler, workers, echo, closure, distributed, checkpoint, resume):
    with phases.timed("prepare"):
        board_obj.prepare(scene, samples)
    # The paper's cost model (5)-(8) sizes the grid. With the hardware's P x R x S parallelism the
    # test term nearly vanishes and it asks for a very coarse grid; the boards here run in
    # software at about one test per 0.05-0.2 us, so the default is the model's optimum for one
    # processor. The hardware optimum is reported alongside.
    voxels_hardware = default_voxels(scene.patches, parallelism=params.processors * params.boards)
    if voxels is None:
        voxels = default_voxels(scene.patches, parallelism=1)
    elif not isinstance(voxels, int) or voxels < 1 or voxels > 256:
        raise ParameterError(f"--voxels must be an integer from 1 to 256, not {voxels!r}")
    with phases.timed("voxelise"):
        grid = VoxelGrid(scene.patch_vertices, voxels, margin=board_obj.margin)
    if distributed:
        return _render_sets(scene, board, board_obj, grid, samples, params, partition=partition, sets=sets,
                            solver=solver, tolerance=tolerance, max_iterations=max_iterations,
                            traversal=traversal, packing=packing, stats_fraction=stats_fraction,
                            scheduler=scheduler, workers=workers, progress=progress, echo=echo,
                            phases=phases, t_start=t_start, voxels=voxels, voxels_hardware=voxels_hardware,
                            checkpoint=checkpoint, resume=resume)
    with phases.timed("load"):
        board_obj.load(grid)

    stats = TraversalStats(grid, sample_fraction=stats_fraction)
    vis = Visibility(scene, board_obj, grid, samples, rows=params.rows, cols=params.cols,
                     traversal=traversal, packing=packing, phases=phases, stats=stats)
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

    bar = _progress(progress, solver, scene.patches if solver != "progressive" or closure != "off" else max_shots)
    saving = None if checkpoint is None else checkpoint.save
    closure_info = factors = None
    with phases.timed("solve"):
        if closure != "off":
            result, closure_info = _solve_closed(scene, shoot, closure, solver, bar, tolerance=tolerance,
                                                 max_shots=max_shots, max_iterations=max_iterations)
        elif solver == "progressive":
            result = solvers.progressive_refinement(scene, shoot, tolerance=tolerance, max_shots=max_shots,
                                                    progress=bar, refuse_gain=True, checkpoint=saving, resume=resume)
        else:
            factors, sums = _columns(scene, shoot, bar)
            result = _solve_matrix(scene, factors, solver, tolerance=tolerance, max_shots=max_shots,
                                   max_iterations=max_iterations, checkpoint=saving, resume=resume)
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

    counters = board_obj.counters()
    report = _report(scene=scene, voxels=voxels, voxels_hardware=voxels_hardware, board_name=board_name,
                     params=params, samples=samples, traversal=traversal, packing=packing,
                     partition=getattr(board_obj, "partition", None), solver=solver, sets=sets, tolerance=tolerance,
                     result=result, rays=vis.rays, blocks=vis.blocks, columns=vis.columns, counters=counters,
                     seconds=seconds, cpu_seconds=cpu_seconds, traversal_stats=stats.summary())
    report["exchange_bytes_per_sweep"] = 0
    if closure_info is not None:
        report["closure"] = closure_info
    _resumed(report, resume)
    return RenderResult(scene=scene, radiosity=result.B, solve=result, report=report, factors=factors)


def _solve_closed(scene, shoot, mode, solver, bar, **solve):
    """Every column of visible factors, made reciprocal / closed (host_driver/closure.py), then
    solved twice with ``solver``: with the corrected factors (the result) and with the raw ones,
    so that the report shows both energy balances side by side."""
    if 8 * scene.patches ** 2 > solvers.MAX_MATRIX_BYTES:
        raise ParameterError(f"--closure {mode}: the form factors of {scene.patches} patches do not fit in "
                             f"{solvers.MAX_MATRIX_BYTES / 2**30:g} GiB", parameter="closure")
    F, sums = _columns(scene, shoot, bar)
    t0 = time.perf_counter()
    corrected, info = closures.enforce(scene, F, mode=mode)
    info["enforce_seconds"] = time.perf_counter() - t0
    result = _solve_matrix(scene, corrected, solver, **solve)
    raw = _solve_matrix(scene, F, solver, **solve)
    result.row_sums = sums                      # of the raw factors: the report's visible_row_sum
    info["absorbed_balance"] = closures.absorbed_balance(scene, result.B).tolist()
    info["absorbed_balance_raw"] = closures.absorbed_balance(scene, raw.B).tolist()
    info["residual_raw"] = float(raw.residual)
    parts = closures.imbalance_terms(scene, F, raw.B)
    info["raw_imbalance_from_closure"], info["raw_imbalance_from_reciprocity"] = (p.tolist() for p in parts)
    return result, info


def _columns(scene, shoot, bar):
    """``(F, row_sums)``: the dense visible factors ``F[j, i]``, one shooter's column at a time,
    each checked as it comes (:class:`~blockray.host_driver.solver.RowSums`)."""
    F = np.zeros((scene.patches, scene.patches))
    sums = solvers.RowSums(refuse_gain=True)
    for i in range(scene.patches):
        F[:, i] = shoot(i)
        sums.check(scene, i, F[:, i])
        if bar is not None:
            bar.update(1)
    return F, sums


def _solve_matrix(scene, F, solver, *, tolerance, max_shots, max_iterations, checkpoint=None, resume=None):
    if solver == "progressive":
        return solvers.progressive_refinement(scene, lambda i: F[:, i], tolerance=tolerance, max_shots=max_shots,
                                              refuse_gain=True)
    gather = solvers.jacobi if solver == "jacobi" else solvers.gauss_seidel
    return gather(scene, F, tolerance=tolerance, max_iterations=max_iterations, checkpoint=checkpoint,
                  resume=resume)


def _resumed(report, resume):
    """The report's ``resumed_from``: the shots or sweeps the checkpoint had done (absent when
    the render started from the beginning)."""
    if resume is not None:
        report["resumed_from"] = {"shots": int(resume["shots"]), "sweeps": int(resume["iterations"])}


def _report(*, scene, voxels, voxels_hardware, board_name, params, samples, traversal, packing, partition, solver,
            sets, tolerance, result, rays, blocks, columns, counters, seconds, traversal_stats, cpu_seconds=None):
    """The keys of ``--report`` (the board's own counters last, never overriding the host's)."""
    report = {
        "scene": scene.name,
        "source": scene.source,
        "patches": int(scene.patches),
        "contact": scene.contact,        # patches split along contact lines at load (None: not done)
        "voxels": int(voxels),
        "voxels_hardware_optimum": int(voxels_hardware),
        "columns_cast": int(columns),
        "board": board_name,
        "board_params": {"rows": params.rows, "cols": params.cols, "boards": params.boards},
        "samples": samples.count,
        "traversal": traversal,
        "packing": packing,
        "partition": partition,
        "solver": solver,
        "sets": int(sets),
        "tolerance": tolerance,
        "shots": int(getattr(result, "shots", 0) or 0),
        "iterations": int(getattr(result, "iterations", 0) or 0),
        "rays": int(rays),
        "blocks": int(blocks),
        "tests": int(counters.get("tests", 0)),
        "tests_per_ray": float(counters.get("tests", 0)) / max(1, rays),
        "residual": float(result.residual),
        "visible_row_sum": result.row_sums.summary() if result.row_sums is not None else None,
        "absorbed_balance": _absorbed_balance(scene, result.B),
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


def _render_sets(scene, board, board_obj, grid, samples, params, *, partition, sets, solver, tolerance,
                 max_iterations, traversal, packing, stats_fraction, scheduler, workers, progress, echo, phases,
                 t_start, voxels, voxels_hardware, checkpoint=None, resume=None):
    """render()'s gathering on ``sets`` host + board sets of a Dask cluster (host_driver/cluster.py),
    from the client's prepared (not loaded) board and voxel grid."""
    from .cluster import SetJob, cluster_client, solve_sets
    bits = board_obj.counters().get("bits")        # the client's quantisation: the B the sets use
    with phases.timed("cluster"), cluster_client(scheduler, workers=workers, sets=sets, echo=echo) as (client, threads):
        job = SetJob(board=board, params=params, bits=bits,
                     partition=partition, samples=samples, traversal=traversal, packing=packing,
                     stats_fraction=stats_fraction, threads=threads)
        owner, result, summaries, info = solve_sets(client, scene, grid, sets, _morton(grid.cell_of(scene.centroids)),
                                                    job, solver=solver, tolerance=tolerance,
                                                    max_iterations=max_iterations, progress=progress,
                                                    checkpoint=None if checkpoint is None else checkpoint.save,
                                                    resume=resume)
    solvers.check_finite(scene, result)
    phases.add("cluster", -(info["assign_seconds"] + info["cast_seconds"] + info["solve_seconds"]))
    phases.add("assign", info["assign_seconds"])
    phases.add("cast", info["cast_seconds"])
    phases.add("solve", info["solve_seconds"])
    for s in summaries:                       # the sets' own phases, summed over the sets
        for phase in ("prepare", "load", "formfactor", "traverse", "board"):
            phases.add(phase, s["phases"].get(phase, 0.0))
    seconds = dict(phases.seconds)
    seconds["total"] = time.perf_counter() - t_start
    stats = TraversalStats(grid)
    for s in summaries:
        stats.add_counts(s["stats"])
    counters = combine_counters(owner, summaries, params.processors * params.boards)
    report = _report(scene=scene, voxels=voxels, voxels_hardware=voxels_hardware, board_name=board, params=params,
                     samples=samples, traversal=traversal, packing=packing,
                     partition=getattr(board_obj, "partition", None), solver=solver, sets=sets, tolerance=tolerance,
                     result=result, rays=sum(s["rays"] for s in summaries),
                     blocks=sum(s["blocks"] for s in summaries), columns=max(s["columns"] for s in summaries),
                     counters=counters, seconds=seconds, traversal_stats=stats.summary())
    report["exchange_bytes_per_sweep"] = int(exchange_bytes_per_sweep(owner))
    report["cluster"] = {
        "scheduler": scheduler or "LocalCluster",
        "workers": [{"address": a, "nthreads": w.get("nthreads")} for a, w in sorted(info["workers"].items())],
        "kernel_threads": threads,
        "exchanged_bytes": int(info["exchanged_bytes"]),
        "exchanges": int(info["exchanges"]),
        "cast_seconds_per_set": [float(s["seconds"]) for s in summaries],
        "cast_cpu_seconds_per_set": [float(s["cpu_seconds"]) for s in summaries],
    }
    _resumed(report, resume)
    return RenderResult(scene=scene, radiosity=result.B, solve=result, report=report)


def _progress(enabled, solver, total):
    if not enabled:
        return None
    from tqdm import tqdm
    unit = "shot" if solver == "progressive" else "column"
    return tqdm(total=total, unit=unit, desc=f"{solver}", leave=False)

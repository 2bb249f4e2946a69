"""The render loop: scene -> board -> form factors -> solver -> outputs.

This is the host of the paper's machine: it voxelises, walks block rays through the grid, sends
them to a board (any :class:`~blockray.host_driver.board.Board` back-end), turns the blocked bits
into visible form factors and solves for radiosity.

Visibility of a (shooter i, receiver j) pair is the fraction of the K rays from i's sample points
to j's centroid that the board reports clear; the form factor is the analytic point-to-triangle
factor from j's centroid to triangle i times that fraction. Rays are cast only for pairs that can
exchange light (:func:`~blockray.host_driver.formfactor.exchange_mask`).
"""

import time
from dataclasses import dataclass, field

import numpy as np

from ..params import BoardParams
from ..samples import SampleScheme
from ..errors import ParameterError
from .board import BlockBatch, BlockBits, ranges
from . import formfactor, solver as solvers, threads as host_threads
from .scaleout import SetVisibility, assign_sets, check_sets, exchange_bytes_per_sweep, receiver_work
from .voxel import VoxelGrid, default_voxels, TraversalStats

__all__ = ["RenderResult", "make_board", "Visibility", "render", "BOARDS", "SOLVERS", "TRAVERSALS"]

BOARDS = ("golden", "model", "amaranth", "verilator")
SOLVERS = ("progressive", "jacobi", "gauss-seidel")
TRAVERSALS = ("block", "ray")
PACKINGS = ("voxel", "fill")


def _morton(ijk):
    """Interleave the bits of voxel coordinates (M, 3) -> (M,) int64 (Z-order)."""
    ijk = np.asarray(ijk, dtype=np.int64)
    code = np.zeros(len(ijk), dtype=np.int64)
    for bit in range(9):
        for axis in range(3):
            code |= ((ijk[:, axis] >> bit) & 1) << (3 * bit + 2 - axis)
    return code


def make_board(name, params=None, *, bits=None, vcd=None, partition="deal"):
    """Build a board back-end by name. ``bits=None`` lets the board choose B for the scene.

    ``amaranth`` / ``verilator``: the board's RTL in the Amaranth simulator or as Verilog under
    Verilator + cocotb (:class:`blockray.sim.rtl_board.RTLBoard`); ``vcd`` (a path) writes their
    waveform."""
    if partition != "deal" and name == "golden":
        raise ParameterError("--partition applies to the hardware's boards; the golden board holds the whole scene")
    if vcd is not None and name not in ("amaranth", "verilator"):
        raise ParameterError(f"--vcd needs a simulated RTL board (--board amaranth or verilator), not {name!r}")
    if name in ("amaranth", "verilator"):
        from ..sim.rtl_board import RTLBoard
        return RTLBoard(params or BoardParams(), bits=bits, backend=name, vcd=vcd, partition=partition)
    if name == "golden":
        from .golden import GoldenBoard
        return GoldenBoard()
    if name == "model":
        from ..sim.model import ModelBoard
        return ModelBoard(params or BoardParams(), bits=bits, partition=partition)
    raise ParameterError(f"--board must be one of {', '.join(BOARDS)}, not {name!r}")


class Phases:
    """Seconds spent per phase: wall clock (``seconds``) and CPU time of the whole process, every
    thread (``cpu``; on a shared machine the steadier measure of the host's own work)."""

    def __init__(self):
        self.seconds = {}
        self.cpu = {}

    def add(self, phase, dt, dcpu=0.0):
        self.seconds[phase] = self.seconds.get(phase, 0.0) + dt
        self.cpu[phase] = self.cpu.get(phase, 0.0) + dcpu

    def timed(self, phase):
        phases = self

        class _T:
            def __enter__(self):
                self.t0, self.c0 = time.perf_counter(), time.process_time()

            def __exit__(self, *exc):
                phases.add(phase, time.perf_counter() - self.t0, time.process_time() - self.c0)
        return _T()


class Visibility:
    """Casts the rays of one shooter to many receivers through the board, as block rays.

    Receivers are grouped by the voxel that holds their end point (the paper's block): each group
    of at most R receivers and each chunk of at most S shooter samples is one block ray.
    ``traversal="ray"`` sends one block per ray with its 3D-DDA voxels instead (the per-ray
    reference, for measuring what block traversal saves).
    """

    def __init__(self, scene, board, grid, samples, *, rows, cols, traversal="block", packing="voxel",
                 phases=None, stats=None):
        if traversal not in TRAVERSALS:
            raise ParameterError(f"--traversal must be one of {', '.join(TRAVERSALS)}, not {traversal!r}")
        self.scene, self.board, self.grid, self.samples = scene, board, grid, samples
        self.rows, self.cols, self.traversal = rows, cols, traversal
        self.phases = phases or Phases()
        self.stats = stats
        self.sample_points = samples.points(scene.patch_vertices)        # (N, K, 3) float
        self.centroids = scene.centroids
        self.end_voxel = grid.voxel_of(self.centroids)
        self.end_morton = _morton(grid.cell_of(self.centroids))
        if packing not in PACKINGS:
            raise ParameterError(f"--packing must be one of {', '.join(PACKINGS)}, not {packing!r}")
        self.packing = packing
        self.nonempty = grid.count > 0
        self.rays = 0
        self.blocks = 0
        self.columns = 0     # shooters whose rays were cast

    def _ray_batch(self, i, receivers):
        """One block per ray (receivers in order, samples inner) with its 3D-DDA voxels."""
        K = self.samples.count
        rec = np.repeat(receivers, K)
        ks = np.tile(np.arange(K), len(receivers))
        with self.phases.timed("traverse"):
            vox, off = self.grid.rays_voxels(self.sample_points[i][ks], self.centroids[rec], nonempty_only=True)
        one = np.arange(len(rec) + 1)
        return BlockBatch(np.full(len(rec), i), ks, one, rec, one, vox, off)

    def _blocks_for(self, i, receivers):
        """The block rays of shooter i to ``receivers``, packed and traversed, as a BlockBatch."""
        if self.traversal == "ray":
            return self._ray_batch(i, receivers)
        K = self.samples.count
        with self.phases.timed("commands"):
            if self.packing == "fill":
                # Fill every row: receivers in Morton order of their end voxels, cut into runs of R.
                # A block then spans neighbouring voxels; its bundle is a little wider.
                rec = receivers[np.argsort(self.end_morton[receivers], kind="stable")]
                first = np.zeros(len(rec), bool)
                first[:1] = True
            else:
                # The paper's block: the receivers whose end points share a voxel.
                rec = receivers[np.argsort(self.end_voxel[receivers], kind="stable")]
                key = self.end_voxel[rec]
                first = np.concatenate([[True], key[1:] != key[:-1]])
            # runs of at most R receivers within each group, times chunks of at most S samples
            group_start = np.flatnonzero(first)
            pos = np.arange(len(rec)) - group_start[np.cumsum(first) - 1]
            run_start = np.flatnonzero(pos % self.rows == 0)
            run_len = np.diff(np.append(run_start, len(rec)))
            chunk_start = np.arange(0, K, self.cols)
            chunk_len = np.minimum(self.cols, K - chunk_start)
            nr, nc = len(run_start), len(chunk_start)
            rows, cols = np.repeat(run_len, nc), np.tile(chunk_len, nr)
            receiver_patch = rec[ranges(np.repeat(run_start, nc), rows)]
            shooter_sample = ranges(np.tile(chunk_start, nr), cols)
            row_off = np.concatenate([[0], np.cumsum(rows)])
            col_off = np.concatenate([[0], np.cumsum(cols)])
            starts, ends = self.sample_points[i][shooter_sample], self.centroids[receiver_patch]
        with self.phases.timed("traverse"):
            vox, vox_off, visited, tests = self.grid.traverse_blocks(starts, col_off, ends, row_off,
                                                                     nonempty_only=True)
            if self.stats is not None:
                self.stats.add_blocks(starts, col_off, ends, row_off, visited, tests)
        return BlockBatch(np.full(len(shooter_sample), i), shooter_sample, col_off, receiver_patch, row_off,
                          vox, vox_off)

    def clear_fraction(self, i, receivers):
        """Fraction of the K rays from shooter i to each receiver that is not blocked."""
        receivers = np.asarray(receivers, dtype=np.int64)
        self.columns += 1
        if len(receivers) == 0:
            return np.zeros(0)
        batch = self._blocks_for(i, receivers)
        with self.phases.timed("board"):
            bits = self.board.run(batch)
        # clear rays per receiver, summed over every block (and sample chunk) it appears in
        if isinstance(bits, BlockBits):
            clear_rays = bits.clear_per_row()
        else:
            clear_rays = np.concatenate([(~np.asarray(b, dtype=bool)).sum(axis=1) for b in bits])
        position = np.empty(self.scene.patches, dtype=np.int64)
        position[receivers] = np.arange(len(receivers))
        clear = np.bincount(position[batch.receiver_patch], weights=clear_rays, minlength=len(receivers))
        self.rays += batch.rays
        self.blocks += len(batch)
        return clear / self.samples.count


@dataclass
class RenderResult:
    scene: object
    radiosity: np.ndarray
    solve: object
    report: dict = field(default_factory=dict)


def render(scene, *, board="golden", params=None, bits=None, voxels=None, samples=8,
           solver="progressive", tolerance=1e-3, max_shots=None, max_iterations=200,
           traversal="block", packing="voxel", partition="deal", sets=1, progress=False,
           stats_fraction=0.02, vcd=None, threads=None):
    """Solve the radiosity of ``scene`` with every visibility query answered by ``board``.

    ``threads``: cores the compiled host kernels use (None: all, see
    :mod:`blockray.host_driver.threads`); the result does not depend on it.
    Returns a :class:`RenderResult` whose ``report`` holds the keys of ``--report``.
    """
    with host_threads.using(threads):
        return _render(scene, board=board, params=params, bits=bits, voxels=voxels, samples=samples,
                       solver=solver, tolerance=tolerance, max_shots=max_shots, max_iterations=max_iterations,
                       traversal=traversal, packing=packing, partition=partition, sets=sets,
                       progress=progress, stats_fraction=stats_fraction, vcd=vcd)


def _render(scene, *, board, params, bits, voxels, samples, solver, tolerance, max_shots, max_iterations,
            traversal, packing, partition, sets, progress, stats_fraction, vcd):
    if solver not in SOLVERS:
        raise ParameterError(f"--solver must be one of {', '.join(SOLVERS)}, not {solver!r}")
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise ParameterError(f"--tolerance must be a positive number, not {tolerance!r}")
    if max_shots is not None and max_shots < 1:
        raise ParameterError(f"--max-shots must be at least 1, not {max_shots!r}")
    params = params or BoardParams()
    if sets != 1:
        if solver == "progressive":
            raise ParameterError("--sets: host + board sets solve by gathering; use --solver jacobi or "
                                 "gauss-seidel", parameter="sets")
        if not isinstance(board, str):
            raise ParameterError("--sets needs a board name (one board is built per set)", parameter="sets")
        check_sets(sets, scene.patches)
    if bits is not None and board == "golden":
        raise ParameterError("--bits applies to boards that quantise the scene; the golden board is float64")
    samples = samples if isinstance(samples, SampleScheme) else SampleScheme(samples)
    phases = Phases()
    t_start, c_start = time.perf_counter(), time.process_time()
    board_obj = (make_board(board, params, bits=bits, vcd=vcd, partition=partition)
                 if isinstance(board, str) else board)
    board_name = board if isinstance(board, str) else board_obj.name

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
    with phases.timed("load"):
        board_obj.load(grid)

    stats = TraversalStats(grid, sample_fraction=stats_fraction)
    vis = Visibility(scene, board_obj, grid, samples, rows=params.rows, cols=params.cols,
                     traversal=traversal, packing=packing, phases=phases, stats=stats)
    owner = None
    if sets != 1:
        # one host + board set per region of the scene (host_driver/scaleout.py); every set loads
        # the whole scene into its own boards and casts the rays ending on its own patches
        with phases.timed("formfactor"):
            work = receiver_work(scene)
        owner = assign_sets(vis.end_morton, sets, work)
        boards, visibilities = [board_obj], [vis]
        for _ in range(sets - 1):
            other = make_board(board, params, bits=bits, partition=partition)
            with phases.timed("prepare"):
                other.prepare(scene, samples)
            with phases.timed("load"):
                other.load(grid)
            boards.append(other)
            visibilities.append(Visibility(scene, other, grid, samples, rows=params.rows, cols=params.cols,
                                           traversal=traversal, packing=packing, phases=phases, stats=stats))
        vis = SetVisibility(owner, visibilities, boards)

    # A patch may shoot more than once; its column of visible form factors does not change.
    cache = {} if scene.patches <= 20000 else None

    def shoot(i):
        if cache is not None and i in cache:
            return cache[i].astype(np.float64)
        with phases.timed("formfactor"):
            # exchange mask applied inside; near receivers averaged over 9 points (reciprocity)
            f_all = formfactor.unoccluded_factors(scene, i)
            receivers = np.flatnonzero(f_all > 0)
            f = f_all[receivers]
        frac = vis.clear_fraction(i, receivers)
        out = np.zeros(scene.patches)
        out[receivers] = f * frac
        if cache is not None:
            cache[i] = out.astype(np.float32) if scene.patches > 4000 else out
        return out

    bar = _progress(progress, solver, scene.patches if solver != "progressive" else max_shots)
    with phases.timed("solve"):
        if solver == "progressive":
            result = solvers.progressive_refinement(scene, shoot, tolerance=tolerance,
                                                    max_shots=max_shots, progress=bar)
        else:
            F = np.zeros((scene.patches, scene.patches))
            for i in range(scene.patches):
                F[:, i] = shoot(i)
                if bar is not None:
                    bar.update(1)
            if solver == "jacobi":
                result = solvers.jacobi(scene, F, tolerance=tolerance, max_iterations=max_iterations)
            elif owner is not None:
                result = solvers.gauss_seidel_sets(scene, F, owner, tolerance=tolerance,
                                                   max_iterations=max_iterations)
            else:
                result = solvers.gauss_seidel(scene, F, tolerance=tolerance, max_iterations=max_iterations)
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

    counters = vis.counters() if owner is not None else board_obj.counters()
    if isinstance(board, str):
        for b in (vis.boards if owner is not None else [board_obj]):
            if hasattr(b, "close"):
                b.close()                   # a simulated board stops its simulator
    report = {
        "scene": scene.name,
        "source": scene.source,
        "patches": int(scene.patches),
        "voxels": int(voxels),
        "voxels_hardware_optimum": int(voxels_hardware),
        "columns_cast": int(vis.columns),
        "board": board_name,
        "board_params": {"rows": params.rows, "cols": params.cols, "boards": params.boards},
        "samples": samples.count,
        "traversal": traversal,
        "packing": packing,
        "partition": getattr(board_obj, "partition", None),
        "solver": solver,
        "sets": int(sets),
        "exchange_bytes_per_sweep": int(exchange_bytes_per_sweep(owner)) if owner is not None else 0,
        "tolerance": tolerance,
        "shots": int(getattr(result, "shots", 0) or 0),
        "iterations": int(getattr(result, "iterations", 0) or 0),
        "rays": int(vis.rays),
        "blocks": int(vis.blocks),
        "tests": int(counters.get("tests", 0)),
        "tests_per_ray": float(counters.get("tests", 0)) / max(1, vis.rays),
        "residual": float(result.residual),
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
        "host_seconds_per_ray": (seconds["commands"] + seconds["traverse"] + seconds["board"]) / max(1, vis.rays),
        "traversal_stats": stats.summary(),
        "threads": host_threads.get(),
    }
    for key, value in counters.items():
        report.setdefault(key, value)
    return RenderResult(scene=scene, radiosity=result.B, solve=result, report=report)


def _progress(enabled, solver, total):
    if not enabled:
        return None
    from tqdm import tqdm
    unit = "shot" if solver == "progressive" else "column"
    return tqdm(total=total, unit=unit, desc=f"{solver}", leave=False)

"""Host + board sets as the workers of a Dask cluster (the paper's section 6, ``--sets K``).

The client (``blockray render``) prepares the scene, builds the voxel grid and assigns every patch
to a set (:func:`~blockray.host_driver.cluster.scaleout.assign_sets`). It then sends the scene, the grid,
the sample scheme, the quantisation (its B; every worker quantises the same scene to the same
grid) and the set assignment to the cluster once (each held by a task, :func:`_hold`), and submits one task per
set (:func:`cast_set`): the worker builds its own board (``make_board``: model, golden, or an RTL
board with its own simulator process), loads the grid, casts the rays that end on its own patches
and keeps its rows of F. Those rows never leave the worker. Each gathering sweep sends the
current radiosities to the workers and brings back each set's new ones
(:func:`~blockray.host_driver.radiosity.solver.jacobi_sweeps`,
:func:`~blockray.host_driver.radiosity.solver.gauss_seidel_sweeps`): only radiosities move.

Faults: the inputs are held as tasks (:func:`_hold`), not scattered, so Dask can make any of them
again; a worker lost while casting, holding its rows or sweeping has its tasks run again on
another worker, and as the cast and the sweeps are deterministic the answer is the same, bit for
bit. The loss of the scheduler, or of every worker for :data:`WORKERLESS` s, ends the render with
:class:`~blockray.errors.ResourceError` (one line, exit 2; :func:`_results`), which a
``--checkpoint`` lets ``--resume`` continue from the last sweep. The cluster is a ``LocalCluster`` on the loopback interface, one worker
process per core (no more than there are sets), started and closed here; or the user's
(``--scheduler ADDRESS``).
"""

import contextlib
import importlib.util
import logging
import os
import time
import warnings
from dataclasses import dataclass

import numpy as np

from ...errors import ParameterError, ResourceError, option
from ..radiosity import formfactor, solver as solvers
from ..board.backends import make_board
from .scaleout import assign_sets, receiver_work
from ..traverse.endpoints import EndPoints
from ..traverse.visibility import Phases, Visibility, visible_fraction
from ...threads import available, set_threads

__all__ = ["SetJob", "SetRows", "cluster_client", "cast_set", "solve_sets", "LOOPBACK", "CONNECT_TIMEOUT"]

#: the only interface a LocalCluster listens on
LOOPBACK = "127.0.0.1"
#: seconds to wait for a user's scheduler before --scheduler is reported unreachable
CONNECT_TIMEOUT = 5
#: seconds between the client's looks at the tasks it waits on (and at the scheduler)
POLL = 0.25
#: seconds a cluster may have no worker before the render ends
WORKERLESS = 10


@contextlib.contextmanager
def cluster_client(scheduler=None, *, workers=None, sets=1, echo=None):
    """A ``dask.distributed.Client``: on a new LocalCluster (``workers`` processes, default one
    per core and at most ``sets``), closed on exit; or connected to ``scheduler``. ``echo(text)``
    is told the dashboard's address when the cluster serves one. Yields ``(client, threads)``,
    ``threads`` the cores each worker's kernels may use (None: the worker's own setting).

    Dask's own logging is silenced (errors only; nothing at all when ``echo`` is None, as with
    ``--quiet``): the render reports a lost cluster itself, in one line. The client and the
    cluster are closed on every path, within seconds even when the scheduler is gone.

    A script that calls this must guard its top level with ``if __name__ == "__main__":``: the
    local workers are spawned processes that import it."""
    from dask.distributed import Client, LocalCluster
    quiet = logging.CRITICAL if echo is None else logging.ERROR
    dask_logger = logging.getLogger("distributed")
    level = dask_logger.level
    dask_logger.setLevel(quiet)
    cluster = None
    if scheduler is None:
        cores = os.cpu_count() or 1
        n = workers or max(1, min(cores, sets))
        threads = max(1, cores // n)
        # one thread per worker: a set's task owns its process; its kernels get `threads` cores
        # The scheduler's HTTP server (dashboard, health) on a free loopback port; the dashboard
        # needs bokeh, which is not a dependency: without it Dask would serve only a notice.
        dashboard = importlib.util.find_spec("bokeh") is not None
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host=LOOPBACK,
                               dashboard_address=f"{LOOPBACK}:0", scheduler_kwargs={"dashboard": dashboard},
                               silence_logs=quiet)
        client = Client(cluster)
    else:
        threads = None
        client = _connect(scheduler)
        dashboard = "dashboard" in client.scheduler_info().get("services", {})
    try:
        if echo is not None and dashboard:
            echo(f"Dask dashboard: {client.dashboard_link}")
        yield client, threads
    except BaseException:
        dask_logger.setLevel(logging.CRITICAL + 1)    # e.g. "failed to reconnect": the error says it
        raise
    finally:
        try:
            client.close(timeout=CONNECT_TIMEOUT)
            if cluster is not None:
                cluster.close(timeout=CONNECT_TIMEOUT)
        except (OSError, TimeoutError, RuntimeError):
            pass                              # a cluster that is gone already
        finally:
            dask_logger.setLevel(level)


def _connect(scheduler):
    from dask.distributed import Client
    if not isinstance(scheduler, str) or not scheduler.strip():
        raise ParameterError(f"{option('scheduler')} must be a scheduler address such as tcp://host:8786, not {scheduler!r}",
                             parameter="scheduler")
    try:
        return Client(scheduler, timeout=CONNECT_TIMEOUT)
    except (OSError, TimeoutError, ValueError) as e:
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ParameterError(f"{option('scheduler')} {scheduler}: no Dask scheduler answered within {CONNECT_TIMEOUT} s "
                             f"({reason})", parameter="scheduler") from None


@dataclass(frozen=True)
class SetJob:
    """What every set's worker needs besides the scene, grid and assignment the cluster holds."""
    board: str
    params: object             # BoardParams, with the B the client quantised to (None: a board without one)
    partition: str
    samples: object            # SampleScheme
    traversal: str
    packing: str
    stats_fraction: float
    end_points: str = "centroid"
    end_seed: int = 0
    end_draws: int = 1
    emitter_factor: int = 1
    threads: object = None     # cores for this worker's compiled kernels (None: its default)
    link_rays: str = "spread"  # the hierarchical solver's (host_driver/render/hierarchical.py)


@dataclass
class SetRows:
    """One set's rows of F, kept on its worker: ``F[r]`` is patch ``own[r]``'s row."""
    own: np.ndarray
    F: np.ndarray
    E: np.ndarray
    rho: np.ndarray
    A: np.ndarray
    summary: dict


class _Receivers:
    """The scene seen from one shooter by one set: its own patches and the shooter, with the
    whole scene's bounding box. :func:`formfactor.unoccluded_factors` depends only on the two
    patches of a pair and the scene's scale, so it gives a set's factors without computing the
    other sets' (tests/test_scaleout.py checks the rows against one set's F bit for bit)."""

    def __init__(self, scene, own):
        self.bbox = scene.bbox
        self._arrays = {name: getattr(scene, name) for name in
                        ("patch_vertices", "centroids", "normals", "reflectance", "areas")}
        self.own = own
        self.position = np.full(scene.patches, -1, dtype=np.int64)
        self.position[own] = np.arange(len(own))

    def factors(self, i):
        """(len(own),) unoccluded ``F_ji`` of the own receivers j to shooter i."""
        at = int(self.position[i])
        index = self.own if at >= 0 else np.append(self.own, i)
        view = _View(self.bbox, {name: a[index] for name, a in self._arrays.items()})
        return formfactor.unoccluded_factors(view, at if at >= 0 else len(self.own))[:len(self.own)]


class _View:
    def __init__(self, bbox, arrays):
        self.bbox = bbox
        self.__dict__.update(arrays)
        self.patches = len(arrays["areas"])


def cast_set(k, scene, grid, owner, job):
    """On a worker: set k builds its board, loads the grid and casts the rays ending on its own
    patches, shooter by shooter. Returns its :class:`SetRows`."""
    from distributed import get_worker
    from ..traverse.cost import TraversalStats
    t0, cpu0 = time.perf_counter(), time.process_time()
    if job.threads is not None:
        set_threads(min(job.threads, available()))
    own = np.flatnonzero(owner == k)
    board = make_board(job.board, job.params, partition=job.partition)
    try:
        phases = Phases()
        with phases.timed("prepare"):
            board.prepare(scene, job.samples)
        with phases.timed("load"):
            board.load(grid)
        stats = TraversalStats(grid, sample_fraction=job.stats_fraction, seed=k)
        vis = Visibility(scene, board, grid, job.samples, rows=job.params.rows, cols=job.params.cols,
                         traversal=job.traversal, packing=job.packing, phases=phases, stats=stats,
                         ends=EndPoints(scene, job.samples, job.end_points, job.end_seed, job.end_draws,
                                        job.emitter_factor))
        receivers = _Receivers(scene, own)
        F = np.zeros((len(own), scene.patches))
        for i in range(scene.patches):
            with phases.timed("formfactor"):
                f = receivers.factors(i)
                solvers.check_factors(i, f, "exact factor")     # a NaN would pass "f > 0" as 0
                take = np.flatnonzero(f > 0)
            F[take, i] = f[take] * visible_fraction(scene, vis, job.samples, i, own[take], phases)
        counters = board.counters()
    finally:
        if hasattr(board, "close"):
            board.close()                    # an RTL board stops its simulator
    A = scene.areas[own]
    summary = {"set": k, "worker": get_worker().address, "patches": len(own), "rays": vis.rays,
               # this set's share of every shooter's row sum and gain (solver.RowSums.of_totals)
               "power": A @ F, "gain": F.T @ (scene.reflectance[own] * A[:, None]),
               "blocks": vis.blocks, "columns": vis.columns, "counters": counters,
               "stats": stats.counts(), "phases": phases.seconds, "seconds": time.perf_counter() - t0,
               "cpu_seconds": time.process_time() - cpu0}
    return SetRows(own=own, F=F, E=scene.emission[own], rho=scene.reflectance[own],
                   A=scene.areas[own], summary=summary)


def _summary(rows):
    return rows.summary


def _jacobi_rows(rows, B):
    return rows.E + rows.rho * solvers.product(rows.F, B)


def _gauss_seidel_rows(rows, B):
    return solvers.set_gauss_seidel(rows.F, rows.own, rows.E, rows.rho, rows.A, B)


def solve_sets(client, scene, grid, sets, morton, job, *, solver, tolerance, max_iterations, progress=False,
               checkpoint=None, resume=None):
    """Assign the patches to ``sets`` sets (:func:`_assign`), cast every set's rows on the
    cluster, then solve by gathering with radiosities exchanged through the cluster.
    Returns ``(owner, SolveResult, summaries, info)``: per set its summary (in set order), and the
    measured ``exchanged_bytes``, ``workers`` and wall seconds of the phases. ``checkpoint``,
    ``resume``: the gathering solvers' (host_driver/radiosity/solver.py), the state saved after each sweep
    and the state to continue from."""
    t0 = time.perf_counter()
    scene_f, grid_f = _hold(client, scene), _hold(client, grid)
    owner = _assign(client, scene, scene_f, sets, morton)
    t1 = time.perf_counter()
    owner_f = _hold(client, owner)
    rows = [client.submit(cast_set, k, scene_f, grid_f, owner_f, job, pure=False) for k in range(sets)]
    summaries = _summaries(client, rows, progress)
    row_sums = solvers.RowSums.of_totals(scene, sum(s["power"] for s in summaries),
                                         sum(s["gain"] for s in summaries), refuse_gain=True)
    t2 = time.perf_counter()
    sweeps = _Sweeps(client, rows, owner)
    bar = _bar(progress, max_iterations, solver, "sweep")
    gather = solvers.jacobi_sweeps if solver == "jacobi" else solvers.gauss_seidel_sweeps
    result = gather(scene, sweeps.jacobi if solver == "jacobi" else sweeps.gauss_seidel, tolerance=tolerance,
                    max_iterations=max_iterations, progress=bar, checkpoint=checkpoint, resume=resume)
    if bar is not None:
        bar.close()
    result.row_sums = row_sums
    info = {"workers": _call(client, client.scheduler_info)["workers"], "exchanged_bytes": sweeps.bytes,
            "exchanges": sweeps.count, "assign_seconds": t1 - t0, "cast_seconds": t2 - t1,
            "solve_seconds": time.perf_counter() - t2}
    return owner, result, summaries, info


def _value(x):
    return x


def _hold(client, value):
    """A future of ``value`` that the cluster can always make again: a task returning it, whose
    spec the scheduler keeps. Dask's memory manager drops the extra replicas of data a client
    scatters, and scattered data whose last copy is lost cannot be made again; a task's result
    lost with its worker is recomputed on a live one, and so is every task that needs it."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sending large graph")
        return client.submit(_value, value, pure=False)


def _lost(client):
    address = getattr(client.scheduler, "address", None) or "its address"
    return ResourceError(f"{option('sets')}: lost the Dask scheduler at {address} (resume from the last "
                         f"{option('checkpoint')} with {option('resume')})")


def _call(client, method, *args):
    """``method(*args)`` on the scheduler; a lost scheduler raises :class:`ResourceError`."""
    from distributed.comm import CommClosedError
    from distributed.utils import CancelledError
    if client.status != "running":
        raise _lost(client)
    try:
        return method(*args)
    except (OSError, CommClosedError, CancelledError):
        raise _lost(client) from None


def _results(client, futures, done=None):
    """The results of ``futures`` (in order) once all are finished, waiting while Dask reruns the
    tasks of a lost worker. ``done(n)`` is told of every ``n`` newly finished. Never hangs: the
    loss of the scheduler (:data:`POLL` s to notice), no worker for :data:`WORKERLESS` s, or a task
    whose workers keep dying raise :class:`ResourceError`; a task's own error is raised as is."""
    from distributed import wait
    from distributed.comm import CommClosedError
    from distributed.scheduler import KilledWorker
    from distributed.utils import CancelledError, TimeoutError
    finished, workerless = 0, None
    while True:
        states = [f.status for f in futures]
        if client.status != "running" or "cancelled" in states:
            raise _lost(client)
        now = states.count("finished")
        if done is not None and now > finished:
            done(now - finished)
        finished = now
        if now == len(futures) or "error" in states:
            break
        if _workers(client):
            workerless = None
        elif workerless is None:
            workerless = time.monotonic()
        elif time.monotonic() - workerless > WORKERLESS:
            raise ResourceError(f"{option('sets')}: the Dask cluster has had no worker for {WORKERLESS} s (resume "
                                f"from the last {option('checkpoint')} with {option('resume')})")
        try:
            wait(futures, timeout=POLL)
        except TimeoutError:
            pass
        except (CommClosedError, CancelledError):
            raise _lost(client) from None
    try:
        return client.gather(futures)
    except KilledWorker as e:
        raise ResourceError(f"{option('sets')}: {e.args[0] if e.args else 'a task'}: every worker that ran it died") from None
    except (CommClosedError, CancelledError):     # the scheduler lost while it gathers them
        raise _lost(client) from None


def _workers(client):
    return len(_call(client, client.scheduler_info)["workers"])


def _assign(client, scene, scene_f, sets, morton):
    """Owner set of every patch: runs of ``morton`` codes of equal
    :func:`~blockray.host_driver.cluster.scaleout.receiver_work`, counted on the cluster (O(N^2))."""
    work = None
    if sets > 1:
        n, parts = scene.patches, 4 * max(1, _workers(client))
        pieces = [client.submit(receiver_work, scene_f, range(n * p // parts, n * (p + 1) // parts), pure=False)
                  for p in range(parts)]
        work = sum(_results(client, pieces))
    return assign_sets(morton, sets, work)


def _summaries(client, rows, progress):
    """Every set's summary, in set order, as the sets finish casting (a progress bar over sets)."""
    bar = _bar(progress, len(rows), "casting", "set")
    summaries = _results(client, [client.submit(_summary, r, pure=False) for r in rows],
                         None if bar is None else bar.update)
    if bar is not None:
        bar.close()
    return summaries


class _Sweeps:
    """Gathering sweeps on the sets' rows: each sends the radiosities B to the workers once, runs
    every set's part and brings back each set's new radiosities. Counts the bytes of the
    exchange: B to every set and each set's part back. (Sets that share a worker share its copy
    of B, and which sets do depends on Dask's placement, which varies from run to run; the
    sets' count does not.)"""

    def __init__(self, client, rows, owner):
        self.client, self.rows = client, rows
        self.groups = [np.flatnonzero(owner == k) for k in range(len(rows))]
        self.bytes = self.count = 0

    def _exchange(self, kernel, B):
        client = self.client
        B_f = _hold(client, B)
        pieces = _results(client, [client.submit(kernel, r, B_f, pure=False) for r in self.rows])
        self.bytes += B.nbytes * len(self.rows) + sum(
            p[1].nbytes + 8 if isinstance(p, tuple) else p.nbytes for p in pieces)   # (weighted, new) or new
        self.count += 1
        return pieces

    def jacobi(self, B):
        new = np.empty_like(B)
        for own, piece in zip(self.groups, self._exchange(_jacobi_rows, B)):
            new[own] = piece
        return new

    def gauss_seidel(self, B):
        new, weighted = np.empty_like(B), 0.0
        for own, (w, piece) in zip(self.groups, self._exchange(_gauss_seidel_rows, B)):
            new[own] = piece
            weighted += w
        return weighted, new


def _bar(enabled, total, desc, unit):
    if not enabled:
        return None
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit=unit, leave=False)

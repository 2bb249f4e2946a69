"""Scale-out (the paper's section 6): K host + board sets solving one scene together.

Each set owns a region of the scene's patches (:func:`assign_sets`: contiguous runs of the
patches in Z-order of their centroids' voxels, so a set's receivers share voxels and its blocks
stay full, cut so that every run receives the same number of rays, :func:`receiver_work`), has its own host and its own P boards, and casts only the rays that end on its own
patches: it computes its rows of the form factor matrix. The sets then solve by gathering and
exchange only patch radiosities (:func:`blockray.host_driver.solver.gauss_seidel_sets`).

:class:`SetVisibility` stands where one :class:`~blockray.host_driver.render.Visibility` stands in
the render loop: ``clear_fraction(i, receivers)`` splits the receivers by owner and asks each
set's own Visibility (and boards). Every ray is the same ray as on one set, and a ray's result
does not depend on the block it travels in (the exact predicate; a block visits a superset of its
rays' voxels), so F, and with the Jacobi solver the radiosity, are identical to one set's.

Machine time: the sets run in parallel, so ``board_cycles`` is the slowest set's;
``set_counters`` lists each set's own counters.
"""

import numpy as np

from ..errors import ParameterError

__all__ = ["check_sets", "assign_sets", "receiver_work", "SetVisibility", "exchange_bytes_per_sweep"]

#: bytes per exchanged radiosity (float32, as the paper's "a few kB/s")
EXCHANGE_BYTES = 4


def check_sets(sets, patches):
    """``sets`` if it is a positive integer no larger than the scene's ``patches``, else
    ParameterError (a set owns at least one patch)."""
    if isinstance(sets, bool) or not isinstance(sets, (int, np.integer)) or sets < 1:
        raise ParameterError(f"--sets must be a positive integer, not {sets!r}", parameter="sets")
    if sets > max(1, patches):
        raise ParameterError(f"--sets {sets} exceeds the scene's {patches} patches (a set owns at least one)",
                             parameter="sets")
    return sets


def assign_sets(morton, sets, weights=None):
    """Owner set (0 .. sets-1) of every patch: the patches sorted by ``morton`` (their centroid
    voxels' Z-order codes) cut into ``sets`` runs, each non-empty, of equal total ``weights``
    (the work a patch brings its set, e.g. :func:`receiver_work`; default 1 per patch: runs of
    equal size to within one)."""
    n = len(morton)
    check_sets(sets, n)
    order = np.argsort(np.asarray(morton), kind="stable")
    owner = np.empty(n, dtype=np.int64)
    if weights is None:
        owner[order] = np.arange(n) * sets // max(1, n)
        return owner
    w = np.asarray(weights, dtype=np.float64)[order]
    if w.shape != (n,) or not np.isfinite(w).all() or (w < 0).any():
        raise ValueError("weights must be finite and >= 0, one per patch")
    before = np.cumsum(w) - w                           # weight of the patches ahead in Z-order
    total = w.sum()
    cut = np.searchsorted(before, total * np.arange(1, sets) / sets, side="left") if total > 0 else \
        np.arange(1, sets) * n // sets
    cut = np.concatenate([[0], cut, [n]])
    for k in range(1, sets):                           # every set keeps at least one patch
        cut[k] = min(max(cut[k], cut[k - 1] + 1), n - (sets - k))
    owner[order] = np.repeat(np.arange(sets), np.diff(cut))
    return owner


def receiver_work(scene):
    """Rays a patch receives, up to the constant samples per shooter: the number of shooters
    that can exchange light with it (:func:`~blockray.host_driver.formfactor.exchange_mask`), the
    pairs the renderer casts rays for. O(N^2) host arithmetic, no rays."""
    from .formfactor import exchange_mask
    work = np.zeros(scene.patches)
    for i in range(scene.patches):
        work += exchange_mask(scene, i)
    return work


def exchange_bytes_per_sweep(owner):
    """Bytes all sets send per gathering sweep: each its own radiosities to every other set."""
    sets = int(owner.max()) + 1 if len(owner) else 1
    return EXCHANGE_BYTES * len(owner) * (sets - 1)


class SetVisibility:
    """K sets' visibility behind one ``clear_fraction``; ``visibilities[k]`` and ``boards[k]`` are
    set k's (see the module docstring)."""

    def __init__(self, owner, visibilities, boards):
        if len(visibilities) != len(boards) or len(boards) != int(owner.max()) + 1:
            raise ValueError("one Visibility and one board per set")
        self.owner = owner
        self.visibilities = visibilities
        self.boards = boards

    def clear_fraction(self, i, receivers, weights=None):
        receivers = np.asarray(receivers, dtype=np.int64)
        out = np.zeros(len(receivers))
        mine = self.owner[receivers]
        for k, vis in enumerate(self.visibilities):
            take = np.flatnonzero(mine == k)
            if len(take):
                out[take] = vis.clear_fraction(i, receivers[take], None if weights is None else weights[take])
        return out

    @property
    def rays(self):
        return sum(v.rays for v in self.visibilities)

    @property
    def blocks(self):
        return sum(v.blocks for v in self.visibilities)

    @property
    def columns(self):
        return max(v.columns for v in self.visibilities)

    def counters(self):
        """The machine's counters: tests summed over the sets, ``board_cycles`` the slowest
        set's (they run in parallel), ``utilization`` over all K x P boards; ``set_counters`` per set."""
        per_set = [b.counters() for b in self.boards]
        out = dict(per_set[0])
        for key in ("tests", "tests_useful", "tests_issued"):
            if key in out:
                out[key] = sum(c[key] for c in per_set)
        out["set_counters"] = [{
            "patches": int((self.owner == k).sum()),
            "rays": int(v.rays),
            "blocks": int(v.blocks),
            **{key: c[key] for key in ("tests", "board_cycles", "utilization") if key in c},
        } for k, (v, c) in enumerate(zip(self.visibilities, per_set))]
        if "board_cycles" in out:
            cycles = max(c["board_cycles"] for c in per_set)
            out["board_cycles"] = cycles
            procs = self.boards[0].params.processors * self.boards[0].params.boards
            out["utilization"] = out["tests_useful"] / (procs * len(per_set) * cycles) if cycles else 0.0
            for key in [k for k in out if k.endswith("_per_board")]:
                out[key] = [x for c in per_set for x in c[key]]      # set 0's boards, then set 1's, ...
        return out

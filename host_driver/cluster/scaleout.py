"""Scale-out (the paper's section 6): K host + board sets solving one scene together.

Each set owns a region of the scene's patches (:func:`assign_sets`: contiguous runs of the
patches in Z-order of their centroids' voxels, so a set's receivers share voxels and its blocks
stay full, cut so that every run receives the same number of rays, :func:`receiver_work`), has its own host and its own P boards, and casts only the rays that end on its own
patches: it computes its rows of the form factor matrix. The sets then solve by gathering and
exchange only patch radiosities (:func:`blockray.host_driver.radiosity.solver.gauss_seidel_sets`).

The sets run as the workers of a Dask cluster (host_driver/cluster/cluster.py). Every ray is the same ray
as on one set, and a ray's result does not depend on the block it travels in (the exact
predicate; a block visits a superset of its rays' voxels), so F, and with the Jacobi solver the
radiosity, are identical to one set's.

Machine time: the sets run in parallel, so ``board_cycles`` is the slowest set's
(:func:`combine_counters`); ``set_counters`` lists each set's own counters.
"""

import numpy as np

from ...errors import ParameterError, option

__all__ = ["check_sets", "assign_sets", "receiver_work", "combine_counters", "exchange_bytes_per_sweep"]

#: bytes per exchanged radiosity (float32, as the paper's "a few kB/s")
EXCHANGE_BYTES = 4


def check_sets(sets, patches):
    """``sets`` if it is a positive integer no larger than the scene's ``patches``, else
    ParameterError (a set owns at least one patch)."""
    if isinstance(sets, bool) or not isinstance(sets, (int, np.integer)) or sets < 1:
        raise ParameterError(f"{option('sets')} must be a positive integer, not {sets!r}", parameter="sets")
    if sets > max(1, patches):
        raise ParameterError(f"{option('sets')} {sets} exceeds the scene's {patches} patches (a set owns at least one)",
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


def receiver_work(scene, shooters=None):
    """Rays a patch receives, up to the constant samples per shooter: the number of shooters
    that can exchange light with it (:func:`~blockray.host_driver.radiosity.formfactor.exchange_mask`), the
    pairs the renderer casts rays for. O(N^2) host arithmetic, no rays. ``shooters`` (a range)
    counts only those shooters; the sums over disjoint ranges add up to the whole (exactly: they
    are counts)."""
    from ..radiosity.formfactor import exchange_mask
    work = np.zeros(scene.patches)
    for i in (range(scene.patches) if shooters is None else shooters):
        work += exchange_mask(scene, i)
    return work


def exchange_bytes_per_sweep(owner):
    """Bytes all sets send per gathering sweep: each its own radiosities to every other set."""
    sets = int(owner.max()) + 1 if len(owner) else 1
    return EXCHANGE_BYTES * len(owner) * (sets - 1)


def combine_counters(owner, summaries, processors):
    """The machine's counters from each set's (``summaries[k]``: set k's ``counters``, ``rays``,
    ``blocks``, and optionally ``worker`` and ``seconds``): tests summed over the sets,
    ``board_cycles`` the slowest set's (they run in parallel), ``utilization`` over all
    K x ``processors`` processors; ``set_counters`` per set."""
    per_set = [s["counters"] for s in summaries]
    out = dict(per_set[0])
    for key in ("tests", "tests_useful", "tests_issued", "blocks", "rays"):
        if key in out:
            out[key] = sum(c[key] for c in per_set)
    out["set_counters"] = [{
        "patches": int((owner == k).sum()),
        "rays": int(s["rays"]),
        "blocks": int(s["blocks"]),
        **{key: c[key] for key in ("tests", "board_cycles", "utilization") if key in c},
        **{key: s[key] for key in ("worker", "seconds") if key in s},
    } for k, (s, c) in enumerate(zip(summaries, per_set))]
    if "board_cycles" in out:
        cycles = max(c["board_cycles"] for c in per_set)
        out["board_cycles"] = cycles
        out["utilization"] = out["tests_useful"] / (processors * len(per_set) * cycles) if cycles else 0.0
        for key in [k for k in out if k.endswith("_per_board")]:
            out[key] = [x for c in per_set for x in c[key]]      # set 0's boards, then set 1's, ...
    return out

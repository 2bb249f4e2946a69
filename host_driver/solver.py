"""Radiosity solvers, RGB throughout: progressive refinement (shooting) and Jacobi / Gauss-Seidel
(gathering).

Notation: N patches, areas A (N,), emission E (N, 3), reflectance rho (N, 3), radiosity B (N, 3).
``F[j, i]`` is the form factor from receiver j to patch i, visibility included (for the host:
the exact patch-to-patch factor times the fraction of clear rays between i and j).

Both families report one comparable error measure, an area-weighted L1 norm over patches and the
three channels relative to the emitted power ``sum_j A_j (E_jr + E_jg + E_jb)``:

- progressive refinement: the unshot energy ``sum A_j U_j / sum A_j E_j`` (the paper's stopping
  rule, eqs. (3)-(4));
- gathering: the residual ``sum A_j |B_j - E_j - rho_j (F B)_j| / sum A_j E_j`` (see :func:`residual`).

In a closed scene with reflectance rho the two are within a factor rho of each other (the
residual of a progressive state is ``rho F U``), so one ``--tolerance`` means the same for all.
"""

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from blockray.errors import ParameterError

__all__ = ["product", "gauss_seidel_sets", "set_gauss_seidel", "gauss_seidel_sweeps", "jacobi_sweeps", "SolveResult",
           "progressive_refinement", "jacobi", "gauss_seidel", "residual", "ambient", "MAX_MATRIX_BYTES",
           "check_matrix_memory"]

#: Largest form-factor matrix the gathering solvers hold: N x N float64 of 8 GiB (N = 32768).
MAX_MATRIX_BYTES = 8 << 30


def check_matrix_memory(patches, solver):
    """Raise :class:`ParameterError` (naming ``--solver``) if a gathering ``solver`` would need a
    form-factor matrix of more than :data:`MAX_MATRIX_BYTES` for ``patches`` patches."""
    need = 8 * patches * patches
    if solver != "progressive" and need > MAX_MATRIX_BYTES:
        raise ParameterError(f"--solver {solver}: the form factors of {patches} patches need "
                             f"{need / 2**30:.3g} GiB, more than {MAX_MATRIX_BYTES / 2**30:g} GiB; use "
                             f"--solver progressive or a larger --max-edge")


@dataclass
class SolveResult:
    """The outcome of a solve."""
    B: np.ndarray                 # (N, 3) radiosity
    U: np.ndarray                 # (N, 3) unshot radiosity (zeros for gathering)
    solver: str
    shots: int = 0                # shooters shot (progressive refinement)
    iterations: int = 0           # sweeps performed (gathering)
    residual: float = 0.0         # relative unshot energy (progressive) / relative residual (gathering)
    converged: bool = False       # residual < tolerance
    history: list = field(default_factory=list)   # history[k]: residual after k shots / sweeps


def _emitted(scene):
    return float((scene.areas[:, None] * scene.emission).sum())


def _relative(scene, per_patch):
    """sum_j A_j * sum_rgb |x_j| / emitted power (0 when both are 0)."""
    num = float((scene.areas[:, None] * np.abs(per_patch)).sum())
    den = _emitted(scene)
    if den == 0:
        return 0.0 if num == 0 else float("inf")
    return num / den


def product(F, B):
    """``F @ B`` with every row summed in the same order whatever rows ``F`` holds, so a host +
    board set's rows of the product are bit-identical to the same rows of the whole product
    (BLAS ``@`` blocks by the matrix's shape and is not)."""
    return np.einsum("ij,jc->ic", F, B)


def residual(scene, F, B):
    """Relative residual of B: ``sum A_j |B_j - E_j - rho_j (F B)_j| / sum A_j E_j`` (RGB summed)."""
    F = _check_matrix(scene, F)
    return _relative(scene, B - scene.emission - scene.reflectance * product(F, B))


def ambient(scene, U):
    """Cohen et al.'s display-only ambient term for a progressive state: ``R * sum A U / sum A``
    with ``R = 1 / (1 - rho_avg)`` (area-averaged reflectance per channel). (3,) RGB."""
    A = scene.areas
    total = A.sum()
    if total == 0:
        return np.zeros(3)
    rho_avg = (A[:, None] * scene.reflectance).sum(axis=0) / total
    return (A[:, None] * U).sum(axis=0) / total / (1 - rho_avg)


def _report(progress, done, res):
    """``progress`` is a tqdm-like object (``update``) or a callable ``progress(done, residual)``."""
    if progress is None:
        return
    if hasattr(progress, "update"):
        progress.update(1)
        if hasattr(progress, "set_postfix"):
            progress.set_postfix(residual=f"{res:.2e}", refresh=False)
    else:
        progress(done, res)


def progressive_refinement(scene, shoot, *, tolerance=1e-3, max_shots=None, progress=None,
                           shoot_many=None, batch=1):
    """Progressive refinement (Cohen et al. 1988; the paper's eqs. (3)-(4)), unshot formulation.

    Start with ``B = U = E``. Each shot picks the shooter i with the largest ``A_i * sum_rgb U_i``
    (energy summed over RGB, the same measure as the stopping rule), gets the visible factors
    ``F_ji`` of every receiver j from ``shoot(i) -> (N,)`` and does
    ``B_j += rho_j U_i F_ji; U_j += rho_j U_i F_ji (j != i); U_i = 0``.
    Stops when the unshot energy ``sum A U / sum A E`` is below ``tolerance`` or after
    ``max_shots`` shots.

    Batched shooting: with ``shoot_many(list of i) -> (len, N)`` and ``batch > 1``, each round
    takes the ``batch`` patches of largest unshot energy, asks for all their rows at once (so the
    caller can fill the board with several shooters) and shoots them in that order, each with its
    unshot radiosity at the moment of its shot (a later shooter may have received from an earlier
    one in the round). A round is shot in full even if the tolerance is reached inside it (the rows
    are already paid for); ``max_shots`` is never exceeded.

    When ``shoot_many`` is given it is used for every round and ``shoot`` may be None.
    Entry i of shooter i's row is ignored (a patch does not shoot at itself).
    """
    A = scene.areas
    E = np.asarray(scene.emission, dtype=np.float64)
    rho = np.asarray(scene.reflectance, dtype=np.float64)
    N = len(A)
    B, U = E.copy(), E.copy()
    if shoot is None and shoot_many is None:
        raise ValueError("progressive_refinement needs shoot or shoot_many")
    if batch < 1:
        raise ValueError(f"batch must be at least 1, not {batch!r}")
    result = SolveResult(B=B, U=U, solver="progressive")
    emitted = _emitted(scene)
    if emitted == 0:
        result.converged = True
        result.history.append(0.0)
        return result
    energy = A * U.sum(axis=1)
    res = float(energy.sum()) / emitted
    result.history.append(res)
    while res >= tolerance and (max_shots is None or result.shots < max_shots):
        k = batch if shoot_many is not None else 1
        if max_shots is not None:
            k = min(k, max_shots - result.shots)
        if shoot_many is None:
            chosen = [int(np.argmax(energy))]
            if energy[chosen[0]] <= 0:
                break
            rows = np.asarray(shoot(chosen[0]), dtype=np.float64)[None]
        else:
            top = np.argsort(-energy, kind="stable")[:k]
            chosen = [int(i) for i in top if energy[i] > 0]
            if not chosen:
                break
            rows = np.asarray(shoot_many(chosen), dtype=np.float64)
        if rows.shape != (len(chosen), N):
            raise ValueError(f"shoot returned rows of shape {rows.shape}, expected {(len(chosen), N)}")
        for i, F in zip(chosen, rows):
            _shoot(B, U, rho, F, i, A, energy)
            result.shots += 1
            res = float(energy.sum()) / emitted
            result.history.append(res)
            _report(progress, result.shots, res)
    result.residual = res
    result.converged = res < tolerance
    return result


@njit(cache=True)
def _shoot(B, U, rho, F, i, A, energy):
    """One shot of patch i with the visible factors F (N,), in place: ``dB_j = rho_j (F_j U_i)``
    (0 for j = i) added to B and U, ``U_i = 0``, ``energy_j = A_j sum_rgb U_j``: the arithmetic of
    the numpy expressions ``rho * (F[:, None] * U[i])``, ``B += dB``, ``A * U.sum(axis=1)``, element
    by element in the same order, without their N x 3 temporaries (one shot per patch shot)."""
    u0, u1, u2 = U[i, 0], U[i, 1], U[i, 2]
    for j in range(len(F)):
        if j == i:
            d0 = d1 = d2 = 0.0
        else:
            d0, d1, d2 = rho[j, 0] * (F[j] * u0), rho[j, 1] * (F[j] * u1), rho[j, 2] * (F[j] * u2)
        B[j, 0] += d0
        B[j, 1] += d1
        B[j, 2] += d2
        U[j, 0] += d0
        U[j, 1] += d1
        U[j, 2] += d2
    U[i, 0] = U[i, 1] = U[i, 2] = 0.0
    for j in range(len(F)):
        energy[j] = A[j] * (U[j, 0] + U[j, 1] + U[j, 2])


def _check_matrix(scene, F):
    F = np.asarray(F, dtype=np.float64)
    if F.shape != (scene.patches, scene.patches):
        raise ValueError(f"F must be ({scene.patches}, {scene.patches}), not {F.shape}")
    return F


def jacobi(scene, F, *, tolerance=1e-3, max_iterations=1000, progress=None):
    """Jacobi gathering ``B <- E + rho * (F @ B)`` from ``B = E``, on a dense F (N, N).

    Stops when :func:`residual` of the current B is below ``tolerance`` or after
    ``max_iterations`` sweeps. The residual of B_k is ``B_k - B_{k+1}``, so it costs no extra
    product: the returned B is the iterate whose residual is reported.
    """
    F = _check_matrix(scene, F)
    E, rho = scene.emission, scene.reflectance
    return jacobi_sweeps(scene, lambda B: E + rho * product(F, B), tolerance=tolerance,
                         max_iterations=max_iterations, progress=progress)


def jacobi_sweeps(scene, sweep, *, tolerance=1e-3, max_iterations=1000, progress=None):
    """:func:`jacobi` with its sweep ``sweep(B) -> E + rho * product(F, B)`` computed elsewhere, e.g. by
    host + board sets that each hold their own rows of F (host_driver/cluster.py)."""
    E = scene.emission
    B = np.array(E, dtype=np.float64)
    result = SolveResult(B=B, U=np.zeros_like(B), solver="jacobi")
    while True:
        new = sweep(B)
        res = _relative(scene, B - new)
        result.history.append(res)
        if res < tolerance or result.iterations >= max_iterations:
            break
        B = new
        result.iterations += 1
        _report(progress, result.iterations, res)
    result.B, result.residual, result.converged = B, res, res < tolerance
    return result


def gauss_seidel(scene, F, *, tolerance=1e-3, max_iterations=1000, progress=None):
    """Gauss-Seidel gathering on a dense F (N, N): sweep j = 0..N-1 in place,
    ``B_j <- E_j + rho_j * sum_i F[j, i] B_i`` with the newest B, from ``B = E``.

    Stops when :func:`residual` of B (one extra product per sweep) is below ``tolerance`` or after
    ``max_iterations`` sweeps. Usually needs about half the sweeps of :func:`jacobi`. It is
    :func:`gauss_seidel_sets` with every patch in one set.
    """
    return gauss_seidel_sets(scene, F, np.zeros(scene.patches, dtype=np.int64), tolerance=tolerance,
                             max_iterations=max_iterations, progress=progress)


def gauss_seidel_sets(scene, F, owner, *, tolerance=1e-3, max_iterations=1000, progress=None):
    """Gauss-Seidel gathering distributed over host + board sets (the paper's section 6).

    ``owner[j]`` is the set that owns patch j. In a sweep every set updates its own patches in
    place, in increasing index, with its own newest values and the other sets' values from the
    last exchange (:func:`set_gauss_seidel`); then the sets exchange their patches' radiosities.
    With one set this is plain Gauss-Seidel (:func:`gauss_seidel`); with every patch its own set
    it is :func:`jacobi`'s update. Stops like :func:`gauss_seidel`. ``result.iterations`` counts
    sweeps (= exchanges).
    """
    F = _check_matrix(scene, F)
    owner = np.asarray(owner, dtype=np.int64)
    if owner.shape != (scene.patches,) or (scene.patches and owner.min() < 0):
        raise ValueError(f"owner must give a set >= 0 for each of the {scene.patches} patches")
    E, rho, A = scene.emission, scene.reflectance, scene.areas
    groups = [np.flatnonzero(owner == k) for k in range(int(owner.max()) + 1 if len(owner) else 0)]
    rows = [F if len(own) == len(F) else F[own] for own in groups]      # one set: no copy of F

    def sweep(B):
        new, weighted = np.empty_like(B), 0.0
        for own, F_rows in zip(groups, rows):
            w, new[own] = set_gauss_seidel(F_rows, own, E[own], rho[own], A[own], B)
            weighted += w
        return weighted, new
    return gauss_seidel_sweeps(scene, sweep, tolerance=tolerance, max_iterations=max_iterations,
                               progress=progress)


def set_gauss_seidel(F_rows, own, E_own, rho_own, A_own, B):
    """One set's part of a Gauss-Seidel sweep over its patches ``own`` (increasing), whose rows of
    F, emission, reflectance and areas are given: ``(weighted, new)``. ``weighted`` is the set's
    share of :func:`residual`'s numerator for B, ``sum A_j |B_j - E_j - rho_j (F B)_j|`` over its
    patches; ``new`` its radiosities after the sweep, updated in place from its newest values and
    the others' values in B."""
    weighted = float((A_own[:, None] * np.abs(B[own] - E_own - rho_own * product(F_rows, B))).sum())
    view = np.array(B, dtype=np.float64)        # what this set holds after the last exchange
    for row, j in enumerate(own):
        view[j] = E_own[row] + rho_own[row] * (F_rows[row] @ view)
    return weighted, view[own]


def gauss_seidel_sweeps(scene, sweep, *, tolerance=1e-3, max_iterations=1000, progress=None):
    """:func:`gauss_seidel_sets` with its sweep computed elsewhere (host_driver/cluster.py):
    ``sweep(B) -> (weighted, B')``, :func:`residual`'s numerator for B summed over the sets, and
    the next iterate. The next iterate of the last sweep is not used."""
    B = np.array(scene.emission, dtype=np.float64)
    emitted = _emitted(scene)
    result = SolveResult(B=B, U=np.zeros_like(B), solver="gauss-seidel")

    def relative(weighted):
        return weighted / emitted if emitted else (0.0 if weighted == 0 else float("inf"))
    weighted, new = sweep(B)
    res = relative(weighted)
    result.history.append(res)
    while res >= tolerance and result.iterations < max_iterations:
        B = new
        result.iterations += 1
        weighted, new = sweep(B)
        res = relative(weighted)
        result.history.append(res)
        _report(progress, result.iterations, res)
    result.B, result.residual, result.converged = B, res, res < tolerance
    return result

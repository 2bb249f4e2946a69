"""Radiosity solvers, RGB throughout: progressive refinement (shooting) and Jacobi / Gauss-Seidel
(gathering).

Notation: N patches, areas A (N,), emission E (N, 3), reflectance rho (N, 3), radiosity B (N, 3).
``F[j, i]`` is the form factor from receiver j to patch i, visibility included (for the host:
the point-to-triangle factor at j's centroid times the fraction of clear rays from i's samples).

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

from blockray.errors import ParameterError

__all__ = ["gauss_seidel_sets", "SolveResult", "progressive_refinement", "jacobi", "gauss_seidel", "residual",
           "ambient", "MAX_MATRIX_BYTES", "check_matrix_memory"]

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


def residual(scene, F, B):
    """Relative residual of B: ``sum A_j |B_j - E_j - rho_j (F B)_j| / sum A_j E_j`` (RGB summed)."""
    F = _check_matrix(scene, F)
    return _relative(scene, B - scene.emission - scene.reflectance * (F @ B))


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
            Ui = U[i].copy()
            dB = rho * (F[:, None] * Ui[None, :])
            dB[i] = 0.0
            B += dB
            U += dB
            U[i] = 0.0
            result.shots += 1
            energy = A * U.sum(axis=1)
            res = float(energy.sum()) / emitted
            result.history.append(res)
            _report(progress, result.shots, res)
    result.residual = res
    result.converged = res < tolerance
    return result


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
    B = np.array(E, dtype=np.float64)
    result = SolveResult(B=B, U=np.zeros_like(B), solver="jacobi")
    while True:
        new = E + rho * (F @ B)
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
    last exchange; then the sets exchange their patches' radiosities. With one set this is plain
    Gauss-Seidel (:func:`gauss_seidel`); with every patch its own set it is :func:`jacobi`'s update.
    Stops like :func:`gauss_seidel`. ``result.iterations`` counts sweeps (= exchanges).
    """
    F = _check_matrix(scene, F)
    owner = np.asarray(owner, dtype=np.int64)
    if owner.shape != (scene.patches,) or (scene.patches and owner.min() < 0):
        raise ValueError(f"owner must give a set >= 0 for each of the {scene.patches} patches")
    E, rho = scene.emission, scene.reflectance
    groups = [np.flatnonzero(owner == k) for k in range(int(owner.max()) + 1 if len(owner) else 0)]
    B = np.array(E, dtype=np.float64)
    result = SolveResult(B=B, U=np.zeros_like(B), solver="gauss-seidel")
    res = residual(scene, F, B)
    result.history.append(res)
    while res >= tolerance and result.iterations < max_iterations:
        new = B.copy()
        for own in groups:
            view = B.copy()                     # what this set holds after the last exchange
            for j in own:
                view[j] = E[j] + rho[j] * (F[j] @ view)
            new[own] = view[own]
        B = new
        result.iterations += 1
        res = residual(scene, F, B)
        result.history.append(res)
        _report(progress, result.iterations, res)
    result.B, result.residual, result.converged = B, res, res < tolerance
    return result

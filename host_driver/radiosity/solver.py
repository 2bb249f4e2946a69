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

**Invariants, checked as the solve runs** (:class:`RowSums`, :func:`check_finite`; a failure raises
:class:`~blockray.errors.SolveError`, which the CLI prints as one line, exit status 2). Every
factor is a finite number >= 0. Write ``s_i = sum_{j != i} A_j F_ji / A_i`` for the fraction of
shooter i's power its factors deliver (``sum_j F_ij`` by reciprocity; <= 1 for exact factors) and
``g_i = max_rgb sum_{j != i} rho_j A_j F_ji / A_i`` for its gain, the fraction that comes back as
unshot light. When every ``g_i <= 1`` (as when ``s_i <= 1`` and ``rho <= 1``), both error measures
never increase: a shot takes ``A_i U_i`` from the unshot energy and gives back at most
``g_i A_i U_i``; in the weighted L1 norm of the residual, a Jacobi sweep maps r to ``rho F r``,
whose norm is at most ``sum_i g_i A_i |r_i|``, and a Gauss-Seidel relaxation of patch i moves
``A_i |r_i|`` of residual to the others, scaled by the same ``g_i`` (so any order, any sets). So a
measure that climbs above its start (:data:`DIVERGED` times it) means wrong factors, and the solve
stops naming the patch.
"""

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from blockray.errors import ParameterError, SolveError, option

__all__ = ["RowSums", "GAIN_ALLOWANCE", "DIVERGED", "check_factors", "column_sums", "check_finite", "product", "gauss_seidel_sets", "set_gauss_seidel", "gauss_seidel_sweeps", "jacobi_sweeps", "SolveResult",
           "progressive_refinement", "jacobi", "gauss_seidel", "residual", "ambient", "MAX_MATRIX_BYTES",
           "check_matrix_memory", "solve_state"]

#: Largest form-factor matrix the gathering solvers hold: N x N float64 of 8 GiB (N = 32768).
MAX_MATRIX_BYTES = 8 << 30


def check_matrix_memory(patches, solver):
    """Raise :class:`ParameterError` (naming ``--solver``) if a gathering ``solver`` would need a
    form-factor matrix of more than :data:`MAX_MATRIX_BYTES` for ``patches`` patches."""
    need = 8 * patches * patches
    if solver != "progressive" and need > MAX_MATRIX_BYTES:
        raise ParameterError(f"{option('solver')} {solver}: the form factors of {patches} patches need "
                             f"{need / 2**30:.3g} GiB, more than {MAX_MATRIX_BYTES / 2**30:g} GiB; use "
                             f"{option('solver')} progressive or a larger {option('max_edge')}")


#: A render refuses a shooter whose factors, after reflection, return more power than it sends:
#: ``g_i = max_rgb sum_{j != i} rho_j A_j F_ji / A_i > 1 + GAIN_ALLOWANCE``. Such a shot makes the
#: unshot energy grow, and a sweep the residual: the one way either solve can diverge (module
#: docstring). Not the row sum ``s_i <= 1`` that exact factors obey: the render's visible factor
#: is the exact factor times the visible fraction of a few rays from i's sample points to j's
#: centroid, and a receiver partly hidden from i whose centroid's rays pass counts as wholly seen,
#: so correct renders have ``s_i`` above 1 where occluders are (model board: 1.0035 on cornell,
#: 1.14 on room, inside the bookshelf); their ``g_i`` stays below 1 (0.72 and 0.79).
#: GAIN_ALLOWANCE is the pair kernel's relative error bound (formfactor.FAR_TARGET, 1e-6), so that
#: a shooter whose exact ``g_i`` is 1 is not refused for the kernel's bounded error; the
#: rounding of the N-term sums (N eps < 1e-10 for N <= 1e6) is far below it.
GAIN_ALLOWANCE = 1e-6

#: A solve is diverged when its error measure (the unshot energy, the residual) exceeds this
#: times its start or is not finite. With every gain ``g_i <= 1`` the measure never rises above
#: its start (module docstring); the factor 2 leaves room for a convergent F with some ``g_i > 1``
#: given to the solvers directly, and a diverging solve, growing geometrically, passes it a few
#: shots or sweeps after it starts to grow.
DIVERGED = 2.0


@dataclass
class RowSums:
    """Per-shooter checks of the visible factors, cheap enough for every shot: :meth:`check`
    refuses a column with a factor that is not a finite number >= 0 and, with ``refuse_gain``, a
    shooter of gain above ``1 + GAIN_ALLOWANCE``; it keeps the largest row sum ``s_i`` (the
    fraction of i's power that lands, ``sum_j F_ij`` by reciprocity) and gain ``g_i`` and
    their patches."""
    refuse_gain: bool = False
    largest: float = 0.0
    patch: int = -1
    gain: float = 0.0
    gain_patch: int = -1
    shot: np.ndarray = field(default=None, repr=False, compare=False)  # (N,) every s_i checked, NaN if not
    _weights: tuple = field(default=None, repr=False, compare=False)   # (A, rho A) of the scene, at the first check

    def check(self, scene, i, F):
        """Check shooter ``i``'s column ``F`` (N,) of visible factors ``F_ji``; returns ``s_i``."""
        if self._weights is None:
            A = np.asarray(scene.areas, dtype=np.float64)
            self._weights = A, np.ascontiguousarray(np.asarray(scene.reflectance, dtype=np.float64) * A[:, None])
        A, rhoA = self._weights
        s, g, ok = _column_sums(np.asarray(F, dtype=np.float64), i, A, rhoA)
        if not ok:
            check_factors(i, F)
        if self.shot is None:
            self.shot = np.full(len(A), np.nan)
        self.shot[i] = s
        if s > self.largest or self.patch < 0:
            self.largest, self.patch = s, int(i)
        if g > self.gain or self.gain_patch < 0:
            self.gain, self.gain_patch = g, int(i)
        if self.refuse_gain and not g <= 1 + GAIN_ALLOWANCE:
            raise _gain_error(i, g, s)
        return s

    @classmethod
    def of_totals(cls, scene, power, gain, refuse_gain=False):
        """From every shooter's ``power = sum_j A_j F_ji`` (N,) and ``gain = sum_j rho_j A_j F_ji``
        (N, 3), summed over the receivers of host + board sets (host_driver/cluster/cluster.py)."""
        A = np.asarray(scene.areas, dtype=np.float64)
        s, g = power / A, gain.max(axis=1) / A
        sums = cls(refuse_gain=refuse_gain, shot=np.array(s, dtype=np.float64))
        if len(A):
            sums.largest, sums.patch = float(s.max()), int(np.argmax(s))
            sums.gain, sums.gain_patch = float(g.max()), int(np.argmax(g))
            if refuse_gain and not sums.gain <= 1 + GAIN_ALLOWANCE:
                raise _gain_error(sums.gain_patch, sums.gain, s[sums.gain_patch])
        return sums

    def blame(self):
        """The clause of a divergence message naming the largest row sum and gain."""
        if self.patch < 0:
            return "no shooter's factors were checked"
        hint = " (form factors wrong?)" if self.largest > 1 else ""
        return (f"the largest visible row sum is patch {self.patch}'s, {self.largest:.6g}{hint}; the largest "
                f"gain patch {self.gain_patch}'s, {self.gain:.6g}")

    def balance_by_group(self, scene, B):
        """Where the light that does not balance comes from: per OBJ group g and channel,
        ``sum_{i in g} A_i B_i (s_i - 1)`` over the emitted power ``sum A E``. At a converged B of a
        scene where every patch reflects, the groups add up to absorbed / emitted - 1 (absorbed
        minus emitted power is ``sum_i A_i B_i (s_i - 1)``). ``{name: [r, g, b]}``; None if a
        shooter's s_i is not known (a resumed solve) or nothing emits."""
        emitted = (scene.emission * scene.areas[:, None]).sum(axis=0)
        if self.shot is None or len(self.shot) != scene.patches or np.isnan(self.shot).any() or not (emitted > 0).all():
            return None
        term = scene.areas[:, None] * B * (self.shot - 1)[:, None] / emitted
        by = np.zeros((max(len(scene.group_names), 1), 3))
        np.add.at(by, scene.group, term)
        names = scene.group_names or ["scene"]
        return {names[g]: by[g].tolist() for g in np.unique(scene.group)}

    def summary(self):
        """The report's ``visible_row_sum``: ``{"max", "patch", "gain_max", "gain_patch"}`` (None
        before any shooter)."""
        if self.patch < 0:
            return None
        return {"max": self.largest, "patch": self.patch, "gain_max": self.gain, "gain_patch": self.gain_patch}


def _gain_error(i, g, s):
    return SolveError(f"form factors wrong: shooter patch {i} would get back {g:.6g} times the light it sends "
                      f"(its visible factors sum to {s:.6g}; sum_j rho_j A_j F_ji / A_i > 1), so the solve would "
                      f"diverge", patch=int(i))


@njit(cache=True)
def _column_sums(F, i, A, rhoA):
    """``(s_i, g_i, ok)`` of shooter i's column F in one pass without branches (:class:`RowSums`);
    ``ok`` is False if a factor is not a finite number >= 0 (a NaN or inf makes ``total`` so)."""
    s = g0 = g1 = g2 = total = 0.0
    low = 0.0
    for j in range(len(F)):
        f = F[j]
        total += f
        low = min(low, f)
        s += A[j] * f
        g0 += rhoA[j, 0] * f
        g1 += rhoA[j, 1] * f
        g2 += rhoA[j, 2] * f
    f = F[i]                            # a patch does not shoot at itself
    s, g0, g1, g2 = s - A[i] * f, g0 - rhoA[i, 0] * f, g1 - rhoA[i, 1] * f, g2 - rhoA[i, 2] * f
    return s / A[i], max(g0, g1, g2) / A[i], low >= 0.0 and np.isfinite(total)


def check_factors(i, F, what="factor"):
    """Raise :class:`SolveError` naming the receiver if a factor ``F_ji`` of shooter ``i``'s column
    ``F`` is not a finite number >= 0 (``what``: the kind of factor, for the message)."""
    if not np.isfinite(F).all() or F.min(initial=0.0) < 0:
        j = int(np.flatnonzero(~(np.isfinite(F) & (F >= 0)))[0])
        raise SolveError(f"form factors wrong: the {what} from patch {j} to shooter patch {i} is {float(F[j])!r}, "
                         f"not a finite number >= 0", patch=int(i))


def column_sums(scene, F, refuse_gain=False):
    """:class:`RowSums` of every column of a dense F (N, N), checked as :meth:`RowSums.check`."""
    sums = RowSums(refuse_gain=refuse_gain)
    for i in range(F.shape[1]):
        sums.check(scene, i, F[:, i])
    return sums


def check_finite(scene, result):
    """Raise :class:`SolveError` naming the first patch whose radiosity is not finite, or if the
    residual is not: nothing non-finite is ever written."""
    bad = np.flatnonzero(~np.isfinite(result.B).all(axis=1))
    if len(bad):
        i = int(bad[0])
        raise SolveError(f"solve diverged: patch {i}'s radiosity is {result.B[i].tolist()} after "
                         f"{_steps(result)}", patch=i)
    if not np.isfinite(result.residual):
        raise SolveError(f"solve diverged: the residual is {result.residual!r} after {_steps(result)}")


def _steps(result):
    if result.solver == "progressive":
        return f"{result.shots} shots"
    return f"{result.iterations} sweeps"


def _check_growth(result, res, what, blame):
    """Raise :class:`SolveError` if the error measure ``res`` is not finite or above
    :data:`DIVERGED` times its start (``blame()``: the clause naming the patch)."""
    start = result.history[0]
    if np.isfinite(res) and res <= DIVERGED * start:
        return
    raise SolveError(f"solve diverged: {what} grew from {start:.3g} to {res:.3g} after {_steps(result)}; "
                     f"{blame()}")


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
    row_sums: RowSums = None      # the largest visible row sum checked (progressive; render's columns)


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
                           shoot_many=None, batch=1, refuse_gain=False, checkpoint=None, resume=None):
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

    Every row is checked (:class:`RowSums`: finite, >= 0, and with ``refuse_gain`` no shooter
    getting back more light than it sends) and the unshot energy must stay finite and below
    :data:`DIVERGED` times its start; else :class:`~blockray.errors.SolveError`, naming the patch.

    ``checkpoint(state)`` is called after every round with the state (:func:`solve_state`) that
    ``resume`` takes to continue exactly where it was: the same shots, bit for bit.
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
    result = SolveResult(B=B, U=U, solver="progressive", row_sums=RowSums(refuse_gain=refuse_gain))
    emitted = _emitted(scene)
    if emitted == 0:
        result.converged = True
        result.history.append(0.0)
        return result
    energy = A * U.sum(axis=1)
    res = float(energy.sum()) / emitted
    result.history.append(res)
    if resume is not None:
        _resume(result, resume, energy=energy)
        res = result.history[-1]
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
            result.row_sums.check(scene, i, F)
            _shoot(B, U, rho, F, i, A, energy)
            result.shots += 1
            res = float(energy.sum()) / emitted
            result.history.append(res)
            _check_growth(result, res, "the unshot energy", result.row_sums.blame)
            _report(progress, result.shots, res)
        if checkpoint is not None:
            checkpoint(solve_state(result, energy=energy))
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


def _blame_sweep(scene, B, new, F):
    """The clause of a gathering divergence message: the largest row sum of the dense ``F`` if
    given, else the first patch whose radiosity is not finite in ``B`` or in the sweep's ``new``,
    else the one the sweep moved most."""
    if F is not None:
        try:
            return column_sums(scene, F).blame()
        except SolveError as e:          # a factor that is not a finite number >= 0
            return str(e)
    for X in (B, new):                  # the first iterate with a non-finite radiosity
        bad = np.flatnonzero(~np.isfinite(X).all(axis=1))
        if len(bad):
            return f"patch {int(bad[0])}'s radiosity became {X[bad[0]].tolist()}"
    moved = scene.areas * np.abs(new - B).sum(axis=1)
    return f"patch {int(np.argmax(moved))}'s radiosity moved most"


def _check_matrix(scene, F):
    F = np.asarray(F, dtype=np.float64)
    if F.shape != (scene.patches, scene.patches):
        raise ValueError(f"F must be ({scene.patches}, {scene.patches}), not {F.shape}")
    return F


def jacobi(scene, F, *, tolerance=1e-3, max_iterations=1000, progress=None, checkpoint=None, resume=None):
    """Jacobi gathering ``B <- E + rho * (F @ B)`` from ``B = E``, on a dense F (N, N).

    Stops when :func:`residual` of the current B is below ``tolerance`` or after
    ``max_iterations`` sweeps. The residual of B_k is ``B_k - B_{k+1}``, so it costs no extra
    product: the returned B is the iterate whose residual is reported.
    """
    F = _check_matrix(scene, F)
    E, rho = scene.emission, scene.reflectance
    return jacobi_sweeps(scene, lambda B: E + rho * product(F, B), tolerance=tolerance,
                         max_iterations=max_iterations, progress=progress, factors=F, checkpoint=checkpoint,
                         resume=resume)


def jacobi_sweeps(scene, sweep, *, tolerance=1e-3, max_iterations=1000, progress=None, factors=None,
                  checkpoint=None, resume=None):
    """:func:`jacobi` with its sweep ``sweep(B) -> E + rho * product(F, B)`` computed elsewhere, e.g. by
    host + board sets that each hold their own rows of F (host_driver/cluster/cluster.py).

    A residual that is not finite or climbs above :data:`DIVERGED` times its start raises
    :class:`~blockray.errors.SolveError` naming the shooter of largest row sum of ``factors`` (the
    dense F, if there is one) or else the patch whose radiosity moved most.

    ``checkpoint(state)`` is called after every sweep, ``resume``: such a state to continue from
    (:func:`solve_state`)."""
    E = scene.emission
    B = np.array(E, dtype=np.float64)
    result = SolveResult(B=B, U=np.zeros_like(B), solver="jacobi")
    if resume is not None:
        B = _resume(result, resume)
    while True:
        new = sweep(B)
        res = _relative(scene, B - new)
        result.history.append(res)
        _check_growth(result, res, "the residual", lambda: _blame_sweep(scene, B, new, factors))
        if res < tolerance or result.iterations >= max_iterations:
            break
        B = new
        result.iterations += 1
        _report(progress, result.iterations, res)
        if checkpoint is not None:
            checkpoint(solve_state(result, B=B))
    result.B, result.residual, result.converged = B, res, res < tolerance
    return result


def gauss_seidel(scene, F, *, tolerance=1e-3, max_iterations=1000, progress=None, checkpoint=None, resume=None):
    """Gauss-Seidel gathering on a dense F (N, N): sweep j = 0..N-1 in place,
    ``B_j <- E_j + rho_j * sum_i F[j, i] B_i`` with the newest B, from ``B = E``.

    Stops when :func:`residual` of B (one extra product per sweep) is below ``tolerance`` or after
    ``max_iterations`` sweeps. Usually needs about half the sweeps of :func:`jacobi`. It is
    :func:`gauss_seidel_sets` with every patch in one set.
    """
    return gauss_seidel_sets(scene, F, np.zeros(scene.patches, dtype=np.int64), tolerance=tolerance,
                             max_iterations=max_iterations, progress=progress, checkpoint=checkpoint, resume=resume)


def gauss_seidel_sets(scene, F, owner, *, tolerance=1e-3, max_iterations=1000, progress=None, checkpoint=None,
                      resume=None):
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
                               progress=progress, factors=F, checkpoint=checkpoint, resume=resume)


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


def gauss_seidel_sweeps(scene, sweep, *, tolerance=1e-3, max_iterations=1000, progress=None, factors=None,
                        checkpoint=None, resume=None):
    """:func:`gauss_seidel_sets` with its sweep computed elsewhere (host_driver/cluster/cluster.py):
    ``sweep(B) -> (weighted, B')``, :func:`residual`'s numerator for B summed over the sets, and
    the next iterate. The next iterate of the last sweep is not used. Stops on a diverging
    residual as :func:`jacobi_sweeps`; checkpoints and resumes as it does."""
    B = np.array(scene.emission, dtype=np.float64)
    emitted = _emitted(scene)
    result = SolveResult(B=B, U=np.zeros_like(B), solver="gauss-seidel")
    if resume is not None:
        B = _resume(result, resume)

    def relative(weighted):
        return weighted / emitted if emitted else (0.0 if weighted == 0 else float("inf"))

    def step(B):
        weighted, new = sweep(B)
        res = relative(weighted)
        result.history.append(res)
        _check_growth(result, res, "the residual", lambda: _blame_sweep(scene, B, new, factors))
        return res, new
    res, new = step(B)
    while res >= tolerance and result.iterations < max_iterations:
        B = new
        result.iterations += 1
        if checkpoint is not None:
            checkpoint(solve_state(result, B=B))
        res, new = step(B)
        _report(progress, result.iterations, res)
    result.B, result.residual, result.converged = B, res, res < tolerance
    return result


def solve_state(result, *, B=None, energy=None):
    """What a solve needs to continue exactly where it is (numpy arrays and numbers; a
    checkpoint, host_driver/render/checkpoint.py): the solver, its radiosity ``B`` (gathering: the
    iterate to sweep next), the unshot ``U`` and per-patch unshot ``energy`` (progressive), the
    shots or sweeps done, the residual history and the largest row sum and gain checked."""
    sums = result.row_sums
    return {"solver": result.solver, "B": np.array(result.B if B is None else B), "U": np.array(result.U),
            "energy": np.zeros(0) if energy is None else np.array(energy), "shots": result.shots,
            "iterations": result.iterations, "history": np.array(result.history, dtype=np.float64),
            "row_sums": np.array([sums.largest, sums.patch, sums.gain, sums.gain_patch]
                                 + ([] if sums.shot is None else list(sums.shot)) if sums is not None
                                 else [], dtype=np.float64)}


def _resume(result, state, energy=None):
    """Load :func:`solve_state`'s ``state`` into ``result`` (and ``energy``, in place); returns B."""
    if state["solver"] != result.solver:
        raise ValueError(f"a {state['solver']} state cannot resume a {result.solver} solve")
    result.B[...] = state["B"]
    result.U[...] = state["U"]
    if energy is not None:
        energy[...] = state["energy"]
    result.shots, result.iterations = int(state["shots"]), int(state["iterations"])
    result.history = [float(x) for x in state["history"]]
    if result.row_sums is not None and len(state["row_sums"]):
        largest, patch, gain, gain_patch = state["row_sums"][:4]
        sums = result.row_sums
        sums.largest, sums.patch, sums.gain, sums.gain_patch = float(largest), int(patch), float(gain), int(gain_patch)
        if len(state["row_sums"]) > 4:
            sums.shot = np.array(state["row_sums"][4:], dtype=np.float64)
    return np.array(result.B)

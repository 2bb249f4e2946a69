"""View-factor enforcement for closed scenes: reciprocity and the summation rule, measured and
(opt-in) restored by symmetric scaling of the exchange-area matrix.

Notation: ``F[j, i]`` is the render's visible form factor from receiver j to shooter i (see
host_driver/radiosity/solver.py); the exchange area ``S[i, j] = A_j F[j, i]`` is the power shooter i
delivers to receiver j per unit of radiosity. Exact view factors satisfy

- reciprocity, ``S = S^T`` (``A_i F_ij = A_j F_ji``), and
- in a closed scene the summation rule ``sum_j S[i, j] = A_i`` (every ray leaving i lands).

Energy balance. For any solution of ``B = E + rho F B`` (and any progressive state shot to the
end), absorbed minus emitted power is ``sum_i B_i (sum_j S[i, j] - A_i)``: only the shooter sums
matter. Split each shooter sum into the closure of the symmetric part and the reciprocity error,

    sum_j S[i, j] / A_i - 1 = [sum_j (S + S^T)[i, j] / 2 / A_i - 1] + sum_j (S - S^T)[i, j] / 2 / A_i,

:func:`diagnose` reports both terms. The antisymmetric term sums to 0 over the scene with area
weights, so it unbalances energy only through differences of B between patches.

Why they are off on the boards: the exact unoccluded factor is reciprocal and closed; the board's
visibility fraction (rays from the shooter's sample points to the receiver's centroid) is
neither symmetric in the pair nor an unbiased estimate of the area-averaged visible fraction.

Enforcement (``mode="enforce"``), the standard step of thermal radiation codes for enclosures
(e.g. ANSYS's VFSM option 2, "row sum equals 1 and reciprocity"; OpenFOAM's view-factor
smoothing for closed surfaces):

1. symmetrise: ``S <- (S + S^T) / 2`` (the mean of both directions' visibility estimates;
   ``mode="symmetric"`` stops here);
2. scale: find ``d > 0`` with ``d_i sum_j S[i, j] d_j = A_i`` for every patch (symmetric
   Sinkhorn-Knopp iteration, ``d <- sqrt(d A / (S d))``), and use ``S' = D S D``.

``S'`` stays symmetric (reciprocity to rounding), its rows sum to ``A_i`` (to rounding), blocked
pairs stay 0 (scaling keeps the zero pattern), and each patch's exchange is scaled by
``d_i d_j``: the report gives ``max |d_i - 1|``. Enforcement assumes the scene is closed: on an
open scene it would push the light that escapes back into the scene, so it is opt-in, and it
refuses a correction larger than ``max_correction``.
"""

import numpy as np

from ...errors import ParameterError, option

__all__ = ["MODES", "exchange_areas", "diagnose", "imbalance_terms", "enforce", "absorbed_balance"]

MODES = ("off", "symmetric", "enforce")

#: Largest ``|d_i - 1|`` :func:`enforce` accepts: beyond it the scene is not closed (or its
#: visibility is too coarse to call it closed) and the correction would hide that.
MAX_CORRECTION = 0.05


def exchange_areas(scene, F):
    """``S[i, j] = A_j F[j, i]`` (N, N): the power shooter i delivers to receiver j per unit B."""
    return (np.asarray(scene.areas, dtype=np.float64)[:, None] * np.asarray(F, dtype=np.float64)).T


def diagnose(scene, F):
    """Reciprocity and summation-rule errors of the render's ``F`` (receiver rows).

    Keys (``A`` the areas, ``S`` the exchange areas, weighted means with weights ``A``):

    - ``shooter_sum``: ``sum_j S[i, j] / A_i - 1`` (what energy balance depends on):
      area-weighted mean, min, max over patches;
    - ``closure``: the same of the symmetric part ``(S + S^T) / 2``; ``closure_lowest``, the five
      patches with the lowest such sums ``[patch, sum - 1]``, and ``closure_below_5pct``, how many
      are more than 5% short;
    - ``reciprocity``: the antisymmetric part's share ``sum_j (S - S^T)[i, j] / 2 / A_i``
      (its weighted mean is 0 by construction): min, max; and ``reciprocity_l1``,
      ``sum |S - S^T| / sum (S + S^T)``, the fraction of exchanged power that is not reciprocal;
      ``reciprocity_max``, ``max |S_ij - S_ji| / max S``;
    - ``gather_sum``: the row sums ``sum_i F[j, i] - 1`` a gathering receiver sees: mean, min, max.
    """
    A = np.asarray(scene.areas, dtype=np.float64)
    S = exchange_areas(scene, F)
    sym, anti = (S + S.T) / 2, (S - S.T) / 2
    shooter = S.sum(axis=1) / A - 1
    closure = sym.sum(axis=1) / A - 1
    recip = anti.sum(axis=1) / A
    gather = np.asarray(F).sum(axis=1) - 1

    def stats(x):
        return {"mean": float((A * x).sum() / A.sum()), "min": float(x.min()), "max": float(x.max())}
    total = float((S + S.T).sum())
    worst = np.argsort(closure, kind="stable")[:5]
    return {"shooter_sum": stats(shooter), "closure": stats(closure),
            "closure_lowest": [[int(i), float(closure[i])] for i in worst],
            "closure_below_5pct": int((closure < -MAX_CORRECTION).sum()),
            "reciprocity": {"min": float(recip.min()), "max": float(recip.max())},
            "reciprocity_l1": float(np.abs(S - S.T).sum() / total) if total else 0.0,
            "reciprocity_max": float(np.abs(S - S.T).max() / S.max()) if S.max() > 0 else 0.0,
            "gather_sum": {"mean": float(np.mean(gather)), "min": float(gather.min()), "max": float(gather.max())}}


def imbalance_terms(scene, F, B):
    """``(closure, reciprocity)``, each (3,): the two parts of ``sum_i B_i (sum_j S[i, j] - A_i)``
    (absorbed minus emitted power of a converged B) over the emitted power, from the symmetric
    part of S (the summation rule) and from its antisymmetric part (reciprocity)."""
    A = np.asarray(scene.areas, dtype=np.float64)
    S = exchange_areas(scene, F)
    emitted = (scene.emission * A[:, None]).sum(axis=0)
    closure = ((S + S.T) / 2).sum(axis=1) - A
    recip = ((S - S.T) / 2).sum(axis=1)
    return (closure[:, None] * B).sum(axis=0) / emitted, (recip[:, None] * B).sum(axis=0) / emitted


def _scale(S, A, *, tol=1e-15, max_iterations=10000):
    """``d`` with ``d_i (S d)_i = A_i`` for every patch with a nonzero row (others keep 1), by the
    symmetric Sinkhorn-Knopp iteration; returns ``(d, iterations)``."""
    d = np.ones(len(A))
    live = S.sum(axis=1) > 0
    for it in range(1, max_iterations + 1):
        Sd = S @ d
        ratio = np.where(live, A / np.where(live, Sd * d, 1.0), 1.0)
        d = d * np.sqrt(ratio)
        if np.abs(ratio - 1).max() <= tol:
            return d, it
    return d, max_iterations


def enforce(scene, F, *, mode="enforce", max_correction=MAX_CORRECTION):
    """``(F', info)``: the render's ``F`` (receiver rows) made reciprocal (``mode="symmetric"``)
    and also closed (``mode="enforce"``), with ``info`` the diagnostics before and after and the
    size of the correction. ``mode="off"`` returns ``F`` unchanged (diagnostics still given).

    Raises :class:`ParameterError` (naming ``--closure``) if a patch's scale moves by more than
    ``max_correction``, or if an emitting patch exchanges with nothing. Patches that exchange
    with nothing and emit nothing (a box's face lying on the floor) keep their zero row
    (``info["isolated_patches"]`` counts them).
    """
    if mode not in MODES:
        raise ParameterError(f"{option('closure')} must be one of {', '.join(MODES)}, not {mode!r}")
    F = np.asarray(F, dtype=np.float64)
    A = np.asarray(scene.areas, dtype=np.float64)
    info = {"mode": mode, "raw": diagnose(scene, F)}
    if mode == "off":
        return F, info
    S = exchange_areas(scene, F)
    S = (S + S.T) / 2
    info["symmetrised_max_change"] = float(np.abs(exchange_areas(scene, F) - S).max() / S.max()) if S.max() > 0 else 0.0
    if mode == "enforce":
        # a patch that sees nothing (e.g. a box's bottom face on the floor) exchanges nothing and
        # keeps d = 1; if it emits, its light has nowhere to go: the scene is not closed for it
        isolated = S.sum(axis=1) <= 0
        lost = np.flatnonzero(isolated & (np.asarray(scene.emission).sum(axis=1) > 0))
        if len(lost):
            raise ParameterError(f"{option('closure')} enforce: patch {int(lost[0])} emits but exchanges light with no other "
                                 f"patch; the scene is not closed", parameter="closure")
        info["isolated_patches"] = int(isolated.sum())
        d, iterations = _scale(S, A)
        correction = float(np.abs(d - 1).max())
        info.update(scale_max_change=correction, scale_iterations=iterations,
                    scale_mean_change=float((A * (d - 1)).sum() / A.sum()))
        if correction > max_correction:
            raise ParameterError(f"{option('closure')} enforce: the summation rule needs a scale change |d - 1| of {correction:.3g} on a patch "
                                 f"(more than {max_correction:g}); the scene is not closed, or its visibility too "
                                 f"coarse to enforce", parameter="closure")
        S = d[:, None] * S * d[None, :]
    # F'[j, i] = S[i, j] / A_j, from the symmetric S
    out = S.T / A[:, None]
    info["corrected"] = diagnose(scene, out)
    return out, info


def absorbed_balance(scene, B):
    """Per channel (3,): absorbed power ``sum (1 - rho) H A`` over emitted ``sum E A``, minus 1,
    with ``H = (B - E) / rho`` the incident flux (patches with rho = 0 absorb nothing they can
    show: counted 0)."""
    rho, E, A = scene.reflectance, scene.emission, scene.areas
    H = np.divide(B - E, rho, out=np.zeros_like(B), where=rho > 0)
    return ((1 - rho) * H * A[:, None]).sum(axis=0) / (E * A[:, None]).sum(axis=0) - 1

"""Where a block ray's row ends on its receiver: the rule behind the raw visibility estimate.

A pair's visible factor is its exact unoccluded factor times the weighted clear fraction of K rays
from the shooter's samples to one end point on the receiver (visibility.py). Which point decides
the estimate's bias (docs/formfactors.md, "The raw visibility estimate's bias"):

- ``centroid``: the receiver's area centroid, the paper's block ray. Unbiased only for the
  area-weighted visible fraction; shadows whose edges fall anywhere across the receiver are
  misweighted towards the part far from the shooter, and contact shadows (which always lie along
  the contact line, away from the centroid) are missed.
- ``kernel``: the receiver's centroid weighted by the point-to-point kernel cos cos / r^2 summed
  over the shooter's samples: removes the first-order (kernel-gradient) part of the bias, not the
  contact shadows.
- ``draw``: a point drawn from that same kernel density over the receiver, per pair, from a hash
  of (seed, shooter, receiver): unbiased for the kernel-weighted fraction up to the density's
  discretisation, contact shadows included, at the price of noise in each pair's estimate.

  ``draws`` rows per pair, each with its own drawn point, average the pair's estimate; row d draws
  from the stratum [d, d + 1) / draws of the density's cumulative distribution, so a pair's rows
  spread over its receiver as the density does, at draws times the rays. A pair whose shooter
  emits gets ``emitter_factor`` times the rows: an emitter's row sum carries the emitted power
  first-hand, so its noise weighs most in the result (docs/formfactors.md).

The density is piecewise constant over the receiver's 16 congruent sub-triangles (two midpoint
subdivisions), each valued at its centroid. End points lie on the samples' 1/D barycentric lattice,
strictly inside the receiver and with no weight a multiple of p (samples.py: off the scene's design
grid), so they are exact integers on the board's grid and exact rationals on the golden board.
Being strictly inside, no point lies in the strip within 1/D of the receiver's edges, where contact
shadows are: ``SampleScheme.end_lattice`` makes D finer to narrow that strip, at a coordinate bit
per doubling.
"""

from functools import lru_cache

import numpy as np

from ...errors import ParameterError
from ...samples import lattice_cells, uniforms
from ..radiosity.elements import level_corners

__all__ = ["ENDS", "EndPoints", "MAX_DRAWS"]

ENDS = ("centroid", "kernel", "draw")
MAX_DRAWS = 64       # rows per pair under ``draw``
_LEVELS = 2          # 4^2 sub-triangles carry the density


class EndPoints:
    """Each (shooter, receiver) pair's end point under ``rule`` (one of :data:`ENDS`), as integer
    barycentric weights over the receiver's corners summing to the sample denominator D."""

    def __init__(self, scene, samples, rule="centroid", seed=0, draws=1, emitter_factor=1):
        if rule not in ENDS:
            raise ParameterError(f"end point rule must be one of {', '.join(ENDS)}, not {rule!r}", parameter="end_points")
        if not 1 <= draws * emitter_factor <= (MAX_DRAWS if rule == "draw" else 1):
            raise ParameterError(f"end_draws {draws} x emitter_factor {emitter_factor} needs the draw rule and at most "
                                 f"{MAX_DRAWS}", parameter="end_draws")
        self.scene, self.samples, self.rule, self.seed, self.draws = scene, samples, rule, int(seed), int(draws)
        self.emitter_factor = int(emitter_factor)
        self.D, self.p = int(samples.denominator), int(samples.prime)

    def weights(self, i, receivers, draw=0):
        """(R, 3) int64 end-point weights of shooter i's pairs with ``receivers`` (the pair's row
        ``draw`` of ``draws``); None for ``centroid`` (the board's own centroids)."""
        return self._ends(i, receivers, [draw])

    def draws_of(self, i):
        """Rows per pair of shooter i: ``draws``, times ``emitter_factor`` if i emits."""
        return self.draws * (self.emitter_factor if self.scene.emission[i].any() else 1)

    def rows(self, i, receivers):
        """(:meth:`draws_of` i R, 3): every row's end weights in turn, the density computed once."""
        return self._ends(i, receivers, range(self.draws_of(i)), self.draws_of(i))

    def _ends(self, i, receivers, draws, strata=None):
        if self.rule == "centroid":
            return None
        receivers = np.asarray(receivers, dtype=np.int64)
        w, members, count, centres = _lattice(self.D, self.p)
        V = self.scene.patch_vertices
        Y = np.einsum("cj,rjd->rcd", centres, V[receivers])                   # (R, C, 3) sub-centroids
        # (K, 3) shooter samples: the first set's, when each row has its own (the density's cost
        # grows with the points; K of them estimate it as well as for one set)
        X = self.samples.points(V[i][None], [i])[0][:self.samples.count]
        g = _kernel_sum(X, self.scene.normals[i], Y, self.scene.normals[receivers])   # (R, C)
        total = g.sum(axis=1)
        lit = total > 0
        cdf = np.cumsum(g, axis=1) / np.where(lit, total, 1)[:, None]
        out = []
        for draw in draws:
            row = np.tile(np.full(3, self.D // 3, dtype=np.int64), (len(receivers), 1))
            if self.rule == "kernel":
                target = (g @ centres)[lit] / total[lit, None]                   # barycentric
                row[lit] = w[np.argmin(((w[None] / self.D - target[:, None]) ** 2).sum(axis=2), axis=1)]
            else:
                # row ``draw`` takes its own stratum of the density's CDF: the pair's rows cover it evenly
                u = (draw + uniforms(self.seed, i, receivers, 2 * draw)) / (strata or self.draws)
                v = uniforms(self.seed, i, receivers, 2 * draw + 1)
                cell = np.minimum((cdf < u[:, None]).sum(axis=1), len(count) - 1)
                pick = members[cell, np.minimum((v * count[cell]).astype(np.int64), count[cell] - 1)]
                row[lit] = w[pick[lit]]
            # a point behind the shooter's plane (a straddling receiver) keeps the centroid, in front
            Q = np.einsum("rk,rkd->rd", row / self.D, V[receivers])
            row[((Q - V[i][0]) @ self.scene.normals[i]) <= 0] = self.D // 3
            out.append(row)
        return np.concatenate(out)


@lru_cache(maxsize=None)
def _lattice(D, p):
    """Allowed weights (L, 3) on the 1/D lattice; per sub-triangle the indices of those inside it
    (padded rows) and their count; the sub-triangles' barycentric centroids (C, 3)."""
    sub = level_corners(_LEVELS)                                       # (C, 3, 3)
    return (*lattice_cells(D, p, sub), sub.mean(axis=1))


def _kernel_sum(X, n_i, Y, n_j):
    """(R, C) sum over the shooter points X (K, 3) of cos cos / r^2 (each cosine clipped at 0) to
    the points Y (R, C, 3) of receivers with normals n_j (R, 3); n_i, n_j need not be unit."""
    d = Y[:, :, None, :] - X[None, None]                                       # (R, C, K, 3)
    r2 = (d * d).sum(-1)
    ci = np.maximum((d * n_i).sum(-1), 0)
    cj = np.maximum(-(d * n_j[:, None, None, :]).sum(-1), 0)
    return (ci * cj / np.maximum(r2, 1e-300) ** 2).sum(axis=2)

"""Quantise a scene onto the board's B-bit integer grid.

Coordinates on the board are unsigned B-bit integers ``0 .. 2**B - 1`` over the scene's own
bounding box, with one uniform step on all three axes (so angles and planarity are kept up to
rounding). A sample point is ``sum_k w_k V_k / D`` with integer weights summing to the sample
denominator ``D`` (:attr:`blockray.samples.SampleScheme.denominator`), so vertices are put on the
coarser lattice of multiples of ``D``::

    step = extent / floor((2**B - 1) / D)        scene units between lattice points (largest extent)
    h    = step / D                              scene units per integer unit
    V_int = D * round((x - lo) / step)           a multiple of D in [0, 2**B - 1]

Then every shooter sample point and every receiver centroid is an exact integer on its patch's
plane (no epsilon, no origin offset). Shared vertices of a mesh are quantised once (from the
scene's vertex array), so a closed mesh stays closed.

**Error.** A vertex moves by at most ``sqrt(3) * step / 2`` (half a lattice step per axis); a
sample point or centroid is a convex combination of its vertices with the same weights before and
after, so it moves by at most the largest displacement of its vertices, and so does every point of a
triangle. :attr:`QuantisedScene.displacement` is the measured maximum.

**Choosing B** (:func:`choose_bits`, "model only what a scene needs"): the fewest bits such that
(1) no triangle of nonzero float area degenerates (integer normal 0: it would silently stop
blocking anything) and (2) the measured displacement is at most ``max_error`` times the bounding-box
diagonal (default ``6e-5``; ``1e-4`` for end points finer than the sample lattice when ``6e-5`` leaves
them no B). See docs/fixed-point.md for why the bound is relative to the diagonal and why these values.
"""

from dataclasses import dataclass, field

import numpy as np

from .errors import CapacityError, ParameterError
from .exact import patch_normals
from .params import MIN_BITS, MAX_BITS, Widths, check_bits

__all__ = ["QuantisedScene", "quantise", "choose_bits", "resolve_bits", "DEFAULT_MAX_ERROR",
           "FINE_POINTS_MAX_ERROR", "MAX_DEGENERATE_FRACTION"]

#: default bound of choose_bits: max vertex displacement / bounding-box diagonal. At 6e-5 the built-in
#: scenes' model-vs-golden radiosity is within 1e-4 in every channel (docs/fixed-point.md)
DEFAULT_MAX_ERROR = 6e-5
#: the bound when end points finer than the sample lattice (``--end-lattice``, hierarchical element
#: levels: one bit each) leave ``max_error`` no B up to MAX_BITS: the finer points then take bits
#: from the vertex lattice, down to the vertex lattice the built-ins had before those points
FINE_POINTS_MAX_ERROR = 1e-4
#: a forced --bits is refused when more than this fraction of the nonzero-area patches degenerate
MAX_DEGENERATE_FRACTION = 0.01


@dataclass(eq=False)
class QuantisedScene:
    """A scene on the B-bit integer grid, as the board holds it.

    bits              B
    D                 sample denominator: every vertex coordinate is a multiple of D
    lo                (3,) float: scene point of integer (0, 0, 0)
    h                 scene units per integer unit
    points            (V, 3) int64: the scene's vertex array on the grid
    vertices          (N, 3, 3) int64: patch corners
    normals           (N, 3) int64: (V1 - V0) x (V2 - V0), the host-precomputed patch constant
    shooters          (N, K, 3) int64: shooter sample points (exact, on the patch plane)
    receivers         (N, 3) int64: receiver end points (patch centroids, exact)
    displacement      max distance (scene units) a vertex moved
    end_displacement  max distance (scene units) a sample point or centroid moved
    collapsed         list of int arrays: groups of distinct float vertices sharing one int point
    degenerate        int array: patches of nonzero float area whose int normal is 0
    bound             the displacement bound B was chosen for (relative to the diagonal; None: forced B)
    """

    bits: int
    D: int
    lo: np.ndarray
    h: float
    points: np.ndarray
    vertices: np.ndarray
    normals: np.ndarray
    shooters: np.ndarray
    receivers: np.ndarray
    displacement: float
    end_displacement: float
    diagonal: float
    collapsed: list = field(default_factory=list)
    degenerate: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    nonzero_area: int = 0
    bound: float = None

    @property
    def widths(self):
        return Widths(self.bits)

    @property
    def step(self):
        """Scene units between vertex lattice points (D integer units)."""
        return self.D * self.h

    def to_scene(self, points):
        """Integer grid points (..., 3) -> scene coordinates (float64)."""
        return self.lo + np.asarray(points, dtype=np.float64) * self.h

    @property
    def margin(self):
        """The registration margin the voxel grid must add. The host registers float triangles
        and traverses float rays; the quantised triangle and segment lie within max(displacement)
        of them (convex combinations with the same weights), so a margin of that much covers
        every hit point. The slack covers float rounding."""
        return max(self.displacement, self.end_displacement) * (1 + 1e-9) + 1e-12 * self.diagonal

    @property
    def relative_error(self):
        """Max vertex displacement / bounding-box diagonal."""
        return self.displacement / self.diagonal if self.diagonal > 0 else 0.0

    def end_points(self, receiver_patch, receiver_weights=None):
        """(R, 3) int64 end points of rows on ``receiver_patch``: the centroids, or the exact points
        of the barycentric ``receiver_weights`` (R, 3), integers summing to D."""
        if receiver_weights is None:
            return self.receivers[receiver_patch]
        w = np.asarray(receiver_weights, dtype=np.int64)
        if len(w) and ((w.sum(axis=1) != self.D).any() or (w < 0).any()):
            raise ValueError(f"end-point weights must be non-negative and sum to D = {self.D}")
        return np.einsum("rk,rkc->rc", w, self.vertices[receiver_patch]) // self.D

    def report(self):
        """Summary dict (for --report and logs)."""
        return {
            "bits": self.bits,
            "denominator": self.D,
            "h": self.h,
            "max_displacement": self.displacement,
            "max_end_displacement": self.end_displacement,
            "relative_error": self.relative_error,
            "max_error_bound": self.bound,
            "collapsed_vertex_groups": len(self.collapsed),
            "collapsed_vertices": int(sum(len(g) for g in self.collapsed)),
            "degenerate_patches": int(len(self.degenerate)),
        }


def _nonzero_area(scene):
    return np.any(scene.cross != 0, axis=1)


def _lattice(scene, D, bits):
    """The vertex lattice of ``bits`` bits and denominator ``D``: ``(lo, h, points, V, normals,
    displacement, diagonal)``; all :func:`choose_bits` needs (its two tests read vertices only)."""
    cells = ((1 << bits) - 1) // D
    vx = np.asarray(scene.vertices, dtype=np.float64)
    used = np.unique(scene.triangles)
    if not np.isfinite(vx[used]).all():
        raise CapacityError("the scene has non-finite vertex coordinates")
    lo, hi = scene.bbox
    lo = np.asarray(lo, dtype=np.float64)
    extent = float(np.max(hi - lo))
    step = extent / cells if extent > 0 else 1.0
    h = step / D
    points = np.clip(np.rint((vx - lo) / step), 0, cells).astype(np.int64) * D
    V = points[scene.triangles]                                          # (N, 3, 3)
    moved = np.linalg.norm(lo + points[used] * h - vx[used], axis=1)
    return lo, h, points, V, patch_normals(V), float(moved.max(initial=0.0)), float(np.linalg.norm(hi - lo))


def quantise(scene, samples, bits):
    """Put ``scene`` on the ``bits``-bit grid with the denominator of ``samples``.

    Raises :class:`ParameterError` (naming --bits) when B is outside the limits or too small to
    hold even one lattice step of D.
    """
    bits = check_bits(bits)
    D = int(samples.denominator)
    if ((1 << bits) - 1) // D < 1:
        raise ParameterError(f"bits {bits} is too small for {samples.count} samples per patch "
                             f"(denominator {D} needs at least {D.bit_length()} bits)", parameter="bits")
    if scene.patches == 0:
        raise CapacityError("the scene has no patches to quantise")
    lo, h, points, V, normals, displacement, diagonal = _lattice(scene, D, bits)
    shooters = samples.points_int(V)
    receivers = samples.centroids_int(V)

    w = Widths(bits)
    assert V.min() >= 0 and V.max() < (1 << w.coord)
    assert np.abs(normals).max(initial=0) < (1 << (w.cross - 1))

    fv = scene.patch_vertices
    ends = np.concatenate([
        np.linalg.norm(lo + shooters * h - samples.points(fv), axis=-1).ravel(),
        np.linalg.norm(lo + receivers * h - scene.centroids, axis=-1)])
    end_displacement = float(ends.max(initial=0.0))

    # distinct float vertices that land on one integer point
    vx, used = np.asarray(scene.vertices, dtype=np.float64), np.unique(scene.triangles)
    upts, inv = np.unique(points[used], axis=0, return_inverse=True)
    collapsed = []
    if len(upts) < len(np.unique(vx[used], axis=0)):
        inv = inv.ravel()
        order = np.argsort(inv, kind="stable")
        cuts = np.flatnonzero(np.diff(inv[order])) + 1
        for g in np.split(order, cuts):
            if len(g) > 1 and len(np.unique(vx[used[g]], axis=0)) > 1:
                collapsed.append(used[g])
    nz = _nonzero_area(scene)
    degenerate = np.flatnonzero(nz & ~np.any(normals != 0, axis=1))
    return QuantisedScene(bits=bits, D=D, lo=lo, h=h, points=points, vertices=V, normals=normals,
                          shooters=shooters, receivers=receivers, displacement=displacement,
                          end_displacement=end_displacement, diagonal=diagonal, collapsed=collapsed,
                          degenerate=degenerate, nonzero_area=int(nz.sum()))


def choose_bits(scene, samples, *, max_error=DEFAULT_MAX_ERROR, fine_points_error=FINE_POINTS_MAX_ERROR):
    """The fewest bits that keep every nonzero-area patch non-degenerate and the max vertex
    displacement within ``max_error`` x the bounding-box diagonal. When ``samples`` has end points
    finer than its sample lattice (denominator above 3p) and no B meets ``max_error``, the bound is
    ``fine_points_error`` instead. Returns ``(bits, bound)``.

    Raises :class:`CapacityError` when even ``MAX_BITS`` bits do not.
    """
    for e in (max_error, fine_points_error):
        if not (np.isfinite(e) and e > 0):
            raise ParameterError(f"max_error must be a positive number, not {e!r}")
    finer = int(samples.denominator) // (3 * int(samples.prime))
    bounds = [max_error] + ([fine_points_error] if finer > 1 and fine_points_error > max_error else [])
    first = max(MIN_BITS, int(samples.denominator).bit_length())
    fallback = None
    if scene.patches == 0:
        raise CapacityError("the scene has no patches to quantise")
    nz = _nonzero_area(scene)
    for bits in range(first, MAX_BITS + 1):     # the vertex lattice alone: the end points do not count here
        _, _, _, _, normals, displacement, diagonal = _lattice(scene, int(samples.denominator), bits)
        degenerate = int((nz & ~np.any(normals != 0, axis=1)).sum())
        met = [b for b in bounds if degenerate == 0 and displacement <= b * diagonal]
        if max_error in met:
            return bits, max_error
        fallback = fallback or (met and (bits, met[0]))
    if fallback:
        return fallback
    why = (f"{degenerate} patches degenerate" if degenerate
           else f"max vertex displacement {displacement:.3g} > {bounds[-1]:g} x diagonal {diagonal:.3g}")
    if finer > 1:
        why += f" (the end points {finer} times finer than the sample lattice take {finer.bit_length() - 1} of the bits)"
    raise CapacityError(f"scene {scene.name!r} cannot be represented with at most {MAX_BITS} "
                        f"coordinate bits: at {MAX_BITS} bits {why}")


def resolve_bits(scene, samples, bits=None, *, max_error=DEFAULT_MAX_ERROR):
    """Quantise with forced ``bits`` (``--bits``) or with :func:`choose_bits`.

    A forced B is refused (:class:`ParameterError` naming --bits) when more than
    :data:`MAX_DEGENERATE_FRACTION` of the nonzero-area patches degenerate, or when every
    nonzero-area patch does. Fewer degenerate patches are only reported (``q.degenerate``).
    """
    if bits is None:
        bits, bound = choose_bits(scene, samples, max_error=max_error)
        q = quantise(scene, samples, bits)
        q.bound = bound
        return q
    q = quantise(scene, samples, bits)
    bad = len(q.degenerate)
    if bad and (bad > MAX_DEGENERATE_FRACTION * q.nonzero_area or bad == q.nonzero_area):
        raise ParameterError(
            f"bits {bits} is too few for scene {scene.name!r}: {bad} of {q.nonzero_area} patches "
            f"degenerate to zero area (more than {MAX_DEGENERATE_FRACTION:.0%}); use more bits or let the "
            f"board choose them", parameter="bits")
    return q

"""Unoccluded form factors: the analytic point-to-triangle (Lambert contour) factor.

The paper's formula (2), ``A_j cos cos / (pi r^2)``, diverges for near patches (centre to centre,
two unit squares sharing an edge at a right angle get 1/pi = 0.318 against the exact 0.200), so
the host uses the exact factor from a
differential receiver area at point p with unit normal n to a whole shooter triangle T
(Lambert's contour integral; Baum, Rushmeier, Winget, SIGGRAPH 1989)::

    F_{dA -> T} = 1/(2 pi) * | sum_k beta_k * n . (R_k x R_{k+1}) / |R_k x R_{k+1}| |
    R_k = V_k - p,  beta_k = angle(R_k, R_{k+1})

evaluated on the part of T in front of the receiver's tangent plane (the triangle is clipped
against ``n . (x - p) >= 0``: what lies behind the receiver contributes nothing). The clipped
polygon is planar, convex and does not contain p, so the contour sum has one sign and its
absolute value is the projected solid angle whatever the vertex order.

Conventions:

- The factor is purely geometric and two-sided in the *shooter*: it is the same whichever side of
  T faces p. Whether T can emit towards p (p in front of T's plane) is decided by
  :func:`exchange_mask`, which the render loop applies before casting rays.
- A point on T's plane (its own patch, a coplanar neighbour, a point on T's edge or vertex, a
  zero-area T) gets 0: the limit from outside T's footprint, and the paper's rule that coplanar
  patches never exchange light. No input gives NaN.
- Receiver j's factor to shooter i, ``F_ji``, estimates the patch-to-patch factor
  ``(1/A_j) integral over A_j of F_{dA -> T_i}``. The centroid rule (one point) makes row sums
  ``sum_i F_ji`` exactly 1 in a closed enclosure (the triangles tile the receiver's hemisphere),
  but reciprocity ``A_j F_ji = A_i F_ij``, exact for true patch factors, then fails by up to ~40%
  for small patches meeting at an edge, and energy is not conserved to better than ~2% when one
  such patch emits. :func:`unoccluded_factors` therefore averages over ``subdivision**2`` points
  on receivers near the shooter (within ``near`` x the patches' radii) and uses the centroid
  elsewhere: on a 4 x 4-per-face cube, column sums ``sum_j A_j F_ji / A_i`` go from 0.91..1.05
  to 0.984..1.013, row sums stay within 2e-3 of 1 (mixing rules within a row costs exactness), and
  a corner patch emitting into a closed box loses 0.4% of the energy instead of 1.5%.
  The ray end point for visibility stays the centroid.
"""

import numpy as np

from ..samples import SampleScheme

__all__ = ["point_to_triangles", "triangle_to_points", "triangle_to_patches",
           "exchange_mask", "unoccluded_factors",
           "form_factor_matrix", "scene_scale", "PLANE_TOLERANCE"]

#: relative (to :func:`scene_scale`) distance under which a point counts as on a plane
PLANE_TOLERANCE = 1e-10


def scene_scale(scene):
    """A length for relative tolerances: max(bounding-box extent, largest |coordinate|).

    Rounding errors of float64 positions scale with the coordinates' magnitude, not only with the
    scene's size, hence the second term.
    """
    lo, hi = scene.bbox
    return float(max(np.max(hi - lo), np.max(np.abs(lo)), np.max(np.abs(hi)), np.finfo(float).tiny))


def _unit(v):
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, norm, out=np.zeros_like(v), where=norm > 0)


def _lambert(points, normals, triangles):
    """F_{dA -> T} for broadcast-compatible points (M,3), normals (M,3), triangles (M,3,3)."""
    p = np.asarray(points, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.float64)
    shape = np.broadcast_shapes(p.shape[:-1], np.shape(normals)[:-1], T.shape[:-2])
    p = np.broadcast_to(p, shape + (3,))
    n = _unit(np.broadcast_to(np.asarray(normals, dtype=np.float64), shape + (3,)))
    T = np.broadcast_to(T, shape + (3, 3))

    R = T - p[..., None, :]                                            # (M, 3, 3)
    # on T's plane (including zero-area T): 0
    m = _unit(np.cross(T[..., 1, :] - T[..., 0, :], T[..., 2, :] - T[..., 0, :]))
    size = np.abs(R).max(axis=(-2, -1))
    off_plane = np.abs(np.einsum("...c,...c->...", m, R[..., 0, :])) > 1e-12 * size

    # Sutherland-Hodgman clip against the tangent plane h = n . (x - p) >= 0: each edge k emits
    # its start vertex if inside and the crossing point if it crosses; 6 slots, invalid ones
    # later filled with the previous valid vertex (a zero-length edge contributes nothing).
    h = np.einsum("...kc,...c->...k", R, n)                            # (M, 3)
    Rn, hn = np.roll(R, -1, axis=-2), np.roll(h, -1, axis=-1)
    crosses = ((h > 0) & (hn < 0)) | ((h < 0) & (hn > 0))
    t = np.divide(h, h - hn, out=np.zeros_like(h), where=crosses)
    X = R + t[..., None] * (Rn - R)
    slots = np.stack([R, X], axis=-2).reshape(shape + (6, 3))
    valid = np.stack([h >= 0, crosses], axis=-1).reshape(shape + (6,))
    last = 5 - np.argmax(valid[..., ::-1], axis=-1)                    # last valid slot (cyclic seed)
    current = np.take_along_axis(slots, last[..., None, None].repeat(3, axis=-1), axis=-2)[..., 0, :]
    filled = np.empty_like(slots)
    for k in range(6):
        current = np.where(valid[..., k, None], slots[..., k, :], current)
        filled[..., k, :] = current

    a, b = filled, np.roll(filled, -1, axis=-2)
    c = np.cross(a, b)
    cn = np.linalg.norm(c, axis=-1)
    beta = np.arctan2(cn, np.einsum("...c,...c->...", a, b))
    cos = np.divide(np.einsum("...kc,...c->...k", c, n), cn, out=np.zeros_like(cn), where=cn > 0)
    F = np.abs((beta * cos).sum(axis=-1)) / (2 * np.pi)
    return np.where(off_plane & valid.any(axis=-1), F, 0.0)


def point_to_triangles(point, normal, triangles):
    """Factors from one differential receiver (point (3,), normal (3,)) to triangles (M,3,3) -> (M,)."""
    T = np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 3)
    return _lambert(np.asarray(point, dtype=np.float64)[None], np.asarray(normal, dtype=np.float64)[None], T)


def triangle_to_points(triangle, points, normals):
    """Factors from many receivers (points (M,3), normals (M,3)) to one shooter triangle (3,3) -> (M,).

    This is the progressive-refinement shape: one shooter i, every receiver j: ``F_ji``.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    return _lambert(p, n, np.asarray(triangle, dtype=np.float64)[None])


def exchange_mask(scene, i):
    """bool (N,): receivers j that can exchange light with shooter i, so rays only where they count.

    j qualifies when all of these hold:

    - j != i, j has non-zero area and a reflectance that is not all zero (a black receiver gains
      nothing from a shot);
    - j's centroid (its ray end point) is strictly in front of i's plane: i emits from its front;
    - some part of triangle i is strictly in front of j's tangent plane at its centroid: otherwise
      the clipped factor is 0 anyway.

    "Strictly" means by more than ``PLANE_TOLERANCE * scene_scale(scene)``, so coplanar
    neighbours (whose float distances are rounding noise) never qualify.
    """
    tol = PLANE_TOLERANCE * scene_scale(scene)
    V = scene.patch_vertices
    c = scene.centroids
    n = scene.normals
    in_front_of_i = (c - V[i, 0]) @ n[i] > tol                              # (N,)
    i_in_front_of_j = np.einsum("jkc,jc->jk", V[i][None] - c[:, None, :], n).max(axis=1) > tol
    mask = in_front_of_i & i_in_front_of_j & (scene.reflectance > 0).any(axis=1) & (scene.areas > 0)
    mask[i] = False
    return mask


def triangle_to_patches(triangle, receivers, normals=None, subdivision=2):
    """Patch-averaged factors from receiver triangles (M,3,3) to one shooter triangle (3,3) -> (M,).

    The midpoint rule over ``subdivision**2`` congruent sub-triangles of each receiver (the cell
    centroids of :class:`~blockray.samples.SampleScheme`): the mean of the point factors. Row sums
    stay exactly 1 in a closed enclosure (each point's hemisphere is tiled), and reciprocity
    errors of the centroid rule fall roughly as 1/subdivision^2. ``normals`` default to the
    receivers' own (V1 - V0) x (V2 - V0).
    """
    R = np.asarray(receivers, dtype=np.float64).reshape(-1, 3, 3)
    if normals is None:
        normals = np.cross(R[:, 1] - R[:, 0], R[:, 2] - R[:, 0])
    k = subdivision * subdivision
    points = SampleScheme(k).points(R)                                   # (M, k, 3)
    f = triangle_to_points(triangle, points.reshape(-1, 3), np.repeat(normals, k, axis=0))
    return f.reshape(len(R), k).mean(axis=1)


def unoccluded_factors(scene, i, *, subdivision=3, near=3.0):
    """(N,) ``F_ji`` from every receiver j to shooter patch i; 0 outside :func:`exchange_mask`.

    Receivers far from i (centroid distance >= ``near`` x the sum of both patches' radii, radius =
    largest centroid-to-vertex distance) use the point factor at their centroid, whose error falls
    as (size / distance)^2; nearer ones average it over ``subdivision**2`` points
    (:func:`triangle_to_patches`), where the centroid rule is worst (patches sharing an edge at
    an angle). ``subdivision=1`` is the plain centroid rule everywhere.
    """
    mask = exchange_mask(scene, i)
    out = np.zeros(scene.patches)
    j = np.flatnonzero(mask)
    V, c, n = scene.patch_vertices, scene.centroids, scene.normals
    if subdivision > 1 and len(j):
        radius = _radii(scene)
        close = np.linalg.norm(c[j] - c[i], axis=1) < near * (radius[j] + radius[i])
        jn, jf = j[close], j[~close]
        out[jn] = triangle_to_patches(V[i], V[jn], n[jn], subdivision)
    else:
        jf = j
    out[jf] = triangle_to_points(V[i], c[jf], n[jf])
    return out


def _radii(scene):
    return np.linalg.norm(scene.patch_vertices - scene.centroids[:, None, :], axis=2).max(axis=1)


def form_factor_matrix(scene, visibility=None, **options):
    """Dense unoccluded ``F[j, i] = F_{dA_j -> T_i}`` (receiver rows, shooter columns), masked.

    ``visibility`` (N, N), optional, multiplies F elementwise (fraction of clear rays). Memory is
    N^2 floats: for small scenes and tests; the render loop builds columns with
    :func:`unoccluded_factors` and the board. ``options`` go to :func:`unoccluded_factors`.
    """
    F = np.zeros((scene.patches, scene.patches))
    for i in range(scene.patches):
        F[:, i] = unoccluded_factors(scene, i, **options)
    if visibility is not None:
        F *= visibility
    return F

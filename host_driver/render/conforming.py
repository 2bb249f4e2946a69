"""The leaves of a hierarchical render as an image mesh without T-vertex cracks.

A leaf next to finer leaves has their corners on its edges (T-vertices). Shaded from its own three
corners, the coarse side interpolates straight along the edge while the fine side passes through
each T-vertex's own value: a crack in the shading. Here every leaf corner and every T-vertex is a
vertex of the mesh, with :func:`~blockray.host_driver.render.image.vertex_radiosity`'s value (the
area-weighted mean of the triangles that share it, within a group and a crease), and a leaf with
T-vertices on its edges is drawn as a fan from its centroid through its corners and T-vertices in
order, the centroid taking the mean of its corners' values (the leaf's linear interpolation there).
Both sides of every edge then interpolate between the same vertices with the same values.

Positions are lattice points of an input triangle, integer barycentric weights over ``2**L``,
computed as ``(w0 V0 + w1 V1 + w2 V2) / 2**L`` in that order: a point on an edge two input
triangles share has two nonzero terms, whose sum does not depend on their order, so it is the same
float from both triangles and T-vertices are found across input triangles too.
"""

import numpy as np

from ..scene.scene import Scene
from .image import vertex_radiosity

__all__ = ["image_mesh", "lattice_points"]


def lattice_points(V, W, L):
    """Float points (M, 3) of integer barycentric weights ``W`` (M, 3) over ``2**L`` on triangles
    ``V`` (M, 3, 3), in the fixed order of the module docstring."""
    W = np.asarray(W, dtype=np.float64)
    return (W[:, 0, None] * V[:, 0] + W[:, 1, None] * V[:, 1] + W[:, 2, None] * V[:, 2]) / float(1 << L) + 0.0


def _edge_candidates(h, leaves):
    """The lattice points strictly inside every leaf edge at the deepest level's spacing:
    ``(leaf, edge, k, points)``, k counting from the edge's first corner (edge e runs from corner
    e to corner e + 1)."""
    L = h.points.max_level
    W = h.points.corners[h.node[leaves]]                               # (n, 3, 3) over 2**L
    steps = 1 << (L - h.level[leaves])
    m = np.repeat(np.arange(len(leaves)), 3 * (steps - 1))
    edge = np.concatenate([np.repeat(np.arange(3), s - 1) for s in steps]) if len(leaves) else np.zeros(0, int)
    k = np.concatenate([np.tile(np.arange(1, s), 3) for s in steps]) if len(leaves) else np.zeros(0, int)
    a, b = W[m, edge], W[m, (edge + 1) % 3]
    weights = a + k[:, None] * (b - a) // steps[m][:, None]
    points = lattice_points(h.scene.patch_vertices[h.patch[leaves[m]]], weights, L)
    return m, edge, k, points


def _polygons(h, leaves, corners):
    """Per leaf, its boundary points in order (corners and T-vertices), for the leaves with
    T-vertices: ``{leaf position m: (P, 3) array}``."""
    m, edge, k, points = _edge_candidates(h, leaves)
    flat = corners.reshape(-1, 3)
    _, ids = np.unique(np.concatenate([flat, points]), axis=0, return_inverse=True)
    ids = ids.ravel()
    is_t = np.isin(ids[len(flat):], ids[:len(flat)])
    m, edge, k, points = m[is_t], edge[is_t], k[is_t], points[is_t]
    order = np.lexsort((k, edge, m))
    m, edge, points = m[order], edge[order], points[order]
    polygons = {}
    for leaf in np.unique(m):
        mine = m == leaf
        parts = []
        for e in range(3):
            parts += [corners[leaf, e][None], points[mine & (edge == e)]]
        polygons[int(leaf)] = np.concatenate(parts)
    return polygons


def image_mesh(result):
    """``(scene, radiosity, colours)``: the image mesh of a hierarchical render's leaves
    (:class:`~blockray.host_driver.render.hierarchical.HierarchicalResult`), each triangle's leaf
    radiosity, and its corners' values (T, 3, 3) for image.render_image."""
    h = result.hierarchy
    leaves = h.leaves()
    L = h.points.max_level
    W = h.points.corners[h.node[leaves]].reshape(-1, 3)
    corners = lattice_points(np.repeat(h.scene.patch_vertices[h.patch[leaves]], 3, axis=0), W, L).reshape(-1, 3, 3)
    polygons = _polygons(h, leaves, corners)
    plain = np.array([m for m in range(len(leaves)) if m not in polygons], dtype=np.int64)
    tris, owner, fan_of = [corners[plain]], [plain], []
    for m, poly in polygons.items():
        centre = np.repeat(corners[m].mean(axis=0)[None], len(poly), axis=0)
        tris.append(np.stack([centre, poly, np.roll(poly, -1, axis=0)], axis=1))
        owner.append(np.full(len(poly), m))
        fan_of.append((m, len(poly)))
    tris, owner = np.concatenate(tris), np.concatenate(owner)
    scene, p = h.scene, h.patch[leaves[owner]]
    mesh = Scene(name=scene.name, vertices=tris.reshape(-1, 3), triangles=np.arange(3 * len(tris)).reshape(-1, 3),
                 reflectance=scene.reflectance[p], emission=scene.emission[p], group=scene.group[p],
                 group_names=list(scene.group_names), camera=scene.camera, source=scene.source)
    B = result.radiosity[owner]
    colours = vertex_radiosity(mesh, B)
    _centres_linear(colours, corners, tris, len(plain), fan_of)
    return mesh, B, colours


def _centres_linear(colours, corners, tris, first, fans):
    """Set each fan's centre value to the mean of its leaf's three corner values (in place)."""
    start = first
    for m, n in fans:
        mine = slice(start, start + n)
        at_corner = [np.flatnonzero((tris[mine, 1] == corners[m, c]).all(axis=1))[0] for c in range(3)]
        colours[mine, 0] = np.mean([colours[start + t, 1] for t in at_corner], axis=0)
        start += n

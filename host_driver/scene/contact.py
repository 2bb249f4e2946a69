"""Contact lines: the part of a patch that an object rests on (or stands in) is cut out.

A wall triangle running under a sconce, or a floor triangle under a block, would spread the light it
receives over the covered part too, where nothing can see it: the light is lost (issue 34). At scene
load every patch is split along the outline of what covers it, and the covered pieces are dropped:
they are enclosed, so they neither receive nor pass on light, and dropping them (rather than giving
them zero reflectance) keeps every remaining patch a lit one.

What covers a point of patch P (in P's plane, on its front side):

- **A coplanar face turned the other way** that overlaps P (a block's bottom face on the floor, a
  sofa's arm against its seat): the overlap is covered, on both faces.
- **A closed contact outline.** Every other triangle leaves a *trace* on P's plane: the edge it
  rests on (two corners in the plane, the third in front), or the segment where it passes through
  the plane in front. The trace's covered side is the object's inside, behind the triangle (objects
  face outwards; a wall's inside is the outside of the room). The patches coplanar with P and facing
  the same way are cut by all traces into faces (noded and polygonised by GEOS through shapely); a
  face is covered when every edge of its outline carries a trace (nothing is open) and at least one
  trace has the face on its covered side. So a sconce's four sides close a rectangle on the wall; a
  bookshelf side's three edges and the wall close its footprint on the floor; the open back of a book
  leaves the shelf under it uncovered; the room's walls close the floor but cover none of it.

Not handled (they are left as they are): an object that touches P only at points or along an open
line (an edge of a slanted board leaning on a wall covers nothing: light reaches both sides); an
object overhanging P's outer edge where no wall closes it; coplanar faces turned the same way
(z-fighting duplicates); one-sided open shells (a ring of faces with no top is taken as closed).

Vertices: P's own corners and the other triangles' corners are kept exactly (they are looked up, not
recomputed); new vertices (a trace crossing P's edge) lie in P's plane. GEOS's overlay is robust
(snap-rounding noder), the pieces are triangulated by constrained Delaunay triangulation (no
needles beyond what the outline forces; ``load_scene`` cuts after subdividing, so that a small
footprint cuts small triangles: builtin.py, ``_finish``), and every step is deterministic.

Tolerance: coordinates written to d decimals are each off by up to half a unit of the last decimal,
delta = 0.5e-d (d is the most decimals any coordinate shows, at least 6: exporters print 6; with
exponent notation, half a unit of the last significant digit, see :func:`rounding`); a
vertex and the plane of P through three such points then disagree by up to about
2 sqrt(3) delta (1 + r / h) (r: the vertex's distance from P's centroid, h: P's smallest height;
the plane tilts by up to 2 sqrt(3) delta / h), plus float64 rounding. See :func:`_plane_tolerance`.
"""

import math

import numpy as np
import shapely
from shapely.geometry import LineString, Polygon
from shapely.geometry.polygon import orient

from ...errors import SceneError
from .scene import Scene

__all__ = ["MIN_DECIMALS", "MIN_DIGITS", "rounding", "split_contacts"]

#: Coordinates are taken as printed to at least this many decimals and significant digits (the
#: usual exporters' defaults: ``%.6f``, ``%g``).
MIN_DECIMALS, MIN_DIGITS = 6, 7


def rounding(vertices):
    """delta, the most a coordinate may be off by: half a unit in the last decimal the coordinates
    show (fixed-point files), or in the last significant digit (exponent notation), whichever is
    smaller for each coordinate; at least :data:`MIN_DECIMALS` and :data:`MIN_DIGITS` are assumed."""
    values = np.unique(np.abs(np.asarray(vertices, dtype=np.float64)))
    values = values[values > 0]
    if not len(values):
        return 0.0
    decimals = max([MIN_DECIMALS] + [len(np.format_float_positional(x, unique=True, trim="-").partition(".")[2])
                                     for x in values])
    digits = max([MIN_DIGITS] + [len(np.format_float_scientific(x, unique=True, trim="-").partition("e")[0]
                                     .replace(".", "")) for x in values])
    last_digit = 10.0 ** (np.floor(np.log10(values)) - digits + 1)
    return float(0.5 * np.max(np.minimum(10.0 ** -decimals, last_digit)))


def _plane_tolerance(delta, scale):
    """The distance two points, each off by delta per coordinate, may disagree by, plus the float64
    rounding of a distance computed from coordinates of magnitude ``scale``."""
    return 2.0 * (math.sqrt(3.0) * delta + 8.0 * np.finfo(np.float64).eps * scale)


class _Geometry:
    """Per-patch planes, sizes and tolerances of ``scene``."""

    def __init__(self, scene, delta):
        self.V = scene.vertices
        self.P = scene.patch_vertices
        self.normal = scene.normals
        self.centroid = scene.centroids
        edges = np.linalg.norm(self.P - np.roll(self.P, -1, axis=1), axis=2)
        self.height = 2.0 * scene.areas / edges.max(axis=1)        # smallest height
        self.diameter = edges.max(axis=1)
        self.delta = rounding(self.V) if delta is None else delta
        self.tol = _plane_tolerance(self.delta, float(np.abs(self.V).max()))   # in-plane matching

    def candidates(self):
        """(i, j) pairs, i != j, whose boxes, grown by i's plane tolerance, overlap."""
        lo, hi = self.P.min(axis=1), self.P.max(axis=1)
        grow = self.tol * (1.0 + 2.0 * self.diameter / self.height)
        lo_g, hi_g = lo - grow[:, None], hi + grow[:, None]
        tree = shapely.STRtree(shapely.box(lo_g[:, 0], lo_g[:, 1], hi_g[:, 0], hi_g[:, 1]))
        i, j = tree.query(shapely.box(lo_g[:, 0], lo_g[:, 1], hi_g[:, 0], hi_g[:, 1]), predicate="intersects")
        keep = (i != j) & (lo_g[i, 2] <= hi_g[j, 2]) & (lo_g[j, 2] <= hi_g[i, 2])
        order = np.lexsort((j[keep], i[keep]))
        return i[keep][order], j[keep][order]


def _sides(geo, i, j):
    """(K, 3) in {-1, 0, 1}: where triangle j[k]'s corners lie against patch i[k]'s plane, and
    their signed distances (K, 3)."""
    Q = geo.P[j]
    s = np.einsum("kvx,kx->kv", Q - geo.P[i, 0][:, None], geo.normal[i])
    r = np.linalg.norm(Q - geo.centroid[i][:, None], axis=2)
    tol = geo.tol * (1.0 + r / geo.height[i][:, None])
    return np.where(np.abs(s) <= tol, 0, np.sign(s)).astype(int), s


def _trace(Q, side, s):
    """The segment (2, 3) triangle Q leaves on the plane in front, or None."""
    if 1 not in side or np.count_nonzero(side == 0) == 1 and -1 not in side:
        return None                                  # behind, or touching at one corner
    points = [Q[k] for k in range(3) if side[k] == 0]
    for k in range(3):
        a, b = k, (k + 1) % 3
        if side[a] * side[b] == -1:                  # passes through the plane on this edge
            points.append(Q[a] + (Q[b] - Q[a]) * (s[a] / (s[a] - s[b])))
    return np.array(points) if len(points) == 2 else None


class _Plane:
    """The patches coplanar with a patch and facing its way, in 2D: the axis most along the normal
    is dropped, so 2D coordinates are copies of 3D ones (exact)."""

    def __init__(self, geo, members):
        self.members = members
        self.axes = [a for a in range(3) if a != int(np.argmax(np.abs(geo.normal[members[0]])))]
        self.normal = geo.normal[members[0]]
        self.union = shapely.unary_union([self.polygon(geo.P[m]) for m in members])
        self.traces = {}                              # triangle -> (2D segment (2, 2), covered side (2,))
        self.covers = {m: [] for m in members}        # member -> 2D polygons of opposite coplanar faces
        # 3D points in the plane by their 2D coordinates, the members' own corners first; other
        # points projecting there (a corner above the plane) are not in the plane and not kept
        self.known = {}
        for v in geo.P[members].reshape(-1, 3):
            self.known.setdefault(tuple(self.flat(v)), v)
        self.fresh = []                               # new points (2D, 3D): neighbours share them

    def flat(self, points):
        return np.asarray(points)[..., self.axes]

    def polygon(self, tri):
        return Polygon(self.flat(tri))

    def add_trace(self, j, segment, q_normal):
        if j in self.traces:                          # found from another member already
            return
        inward = -(q_normal - np.dot(q_normal, self.normal) * self.normal)   # into the object, in the plane
        self.traces[j] = (self.flat(segment), self.flat(inward))
        self.remember(segment)

    def add_cover(self, i, tri):
        self.covers[i].append(self.polygon(tri))
        self.remember(tri)

    def remember(self, points):
        for v in points:
            self.known.setdefault(tuple(self.flat(v)), v)


def _planes(geo, n):
    """The planes (groups of coplanar same-facing patches) holding traces or covers."""
    parent = list(range(n))

    def root(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    I, J = geo.candidates()
    side, s = _sides(geo, I, J)
    coplanar = ~side.any(axis=1)
    same = coplanar & (np.einsum("kx,kx->k", geo.normal[I], geo.normal[J]) > 0)
    for i, j in zip(I[same], J[same]):
        parent[max(root(i), root(j))] = min(root(i), root(j))
    found = [(i, j, None) for i, j in zip(I[coplanar & ~same], J[coplanar & ~same])]
    may = (side == 1).any(axis=1) & ((side == -1).any(axis=1) | ((side == 0).sum(axis=1) == 2))
    for k in np.flatnonzero(may):
        segment = _trace(geo.P[J[k]], side[k], s[k])
        if segment is not None:
            found.append((I[k], J[k], segment))
    groups = {}
    for m in range(n):
        groups.setdefault(root(m), []).append(m)
    planes = {}
    for i, j, segment in found:
        r = root(i)
        plane = planes.get(r) or planes.setdefault(r, _Plane(geo, groups[r]))
        if segment is None:
            plane.add_cover(i, geo.P[j])
        else:
            plane.add_trace(j, segment, geo.normal[j])
    return [planes[r] for r in sorted(planes)]


def _covered_faces(plane, tol):
    """The union of the plane's faces closed by traces with one trace's inside toward them."""
    if not plane.traces:
        return shapely.Polygon()
    boundary = plane.union.boundary
    lines = [shapely.snap(LineString(seg), boundary, tol) for seg, _ in plane.traces.values()]
    faces = shapely.get_parts(shapely.polygonize(shapely.get_parts(shapely.unary_union(lines + [boundary]))))
    seg = np.array([s for s, _ in plane.traces.values()])         # (C, 2, 2)
    inward = np.array([w for _, w in plane.traces.values()])      # (C, 2)
    covered = [f for f in faces if _face_covered(orient(f, 1.0), seg, inward, tol)]
    return shapely.unary_union(covered) if covered else shapely.Polygon()


def _face_covered(face, seg, inward, tol):
    rings = [np.asarray(face.exterior.coords)] + [np.asarray(r.coords) for r in face.interiors]
    a = np.concatenate([r[:-1] for r in rings])
    b = np.concatenate([r[1:] for r in rings])
    mid = 0.5 * (a + b)
    d = seg[:, 1] - seg[:, 0]
    t = np.clip(np.einsum("ecx,cx->ec", mid[:, None] - seg[None, :, 0], d) / np.einsum("cx,cx->c", d, d), 0, 1)
    near = np.linalg.norm(mid[:, None] - (seg[None, :, 0] + t[..., None] * d), axis=2) <= tol   # (E, C)
    left = np.stack([a[:, 1] - b[:, 1], b[:, 0] - a[:, 0]], axis=1)     # the face lies to the left
    inside = near & (left @ inward.T > 0)
    return bool(near.any(axis=1).all() and inside.any())


def _lift(plane, geo, i, points2):
    """3D points of patch i for 2D points: a known vertex where one projects there, else on i's plane."""
    k = 3 - sum(plane.axes)
    n, p0 = geo.normal[i], geo.P[i, 0]
    out = np.empty((len(points2), 3))
    for r, (u, v) in enumerate(points2):
        hit = plane.known.get((u, v))
        if hit is None:
            # a trace crossing an edge two patches share: each computes the crossing, a few ulps
            # apart; the second takes the first's point, so that the edge is not cracked
            hit = next((q for p, q in plane.fresh if abs(p[0] - u) + abs(p[1] - v) <= geo.tol), None)
        if hit is None:
            hit = np.empty(3)
            hit[plane.axes] = u, v
            hit[k] = p0[k] - (n[plane.axes[0]] * (u - p0[plane.axes[0]])
                              + n[plane.axes[1]] * (v - p0[plane.axes[1]])) / n[k]
            plane.fresh.append(((u, v), hit))
        out[r] = hit
    return out


def _pieces(plane, geo, i, covered):
    """Patch i's uncovered part as (M, 3, 3) triangles facing its way, the covered pieces' count
    and area; None if nothing of it is covered."""
    tri = plane.polygon(geo.P[i])
    if not plane.covers[i] and not shapely.intersects(covered, tri):
        return None
    stretch = 1.0 / abs(geo.normal[i, 3 - sum(plane.axes)])     # patch i's 3D area over its 2D area
    cover = shapely.unary_union([covered] + plane.covers[i]) if plane.covers[i] else covered
    cover = shapely.intersection(shapely.snap(cover, tri, geo.tol), tri)
    slack = geo.tol * tri.length                    # area of a band as wide as the tolerance
    if cover.area <= slack:
        return None
    rest = shapely.difference(tri, cover)
    parts = [p for p in shapely.get_parts(cover) if p.area > slack]
    if rest.area <= slack:
        return np.zeros((0, 3, 3)), len(parts), tri.area * stretch
    corners = np.array([np.asarray(t.exterior.coords)[:3]
                        for t in shapely.get_parts(shapely.constrained_delaunay_triangles(rest))])
    out = _lift(plane, geo, i, corners.reshape(-1, 2)).reshape(-1, 3, 3)
    cross = np.cross(out[:, 1] - out[:, 0], out[:, 2] - out[:, 0])
    longest = np.linalg.norm(out - np.roll(out, -1, axis=1), axis=2).max(axis=1)
    wide = np.linalg.norm(cross, axis=1) > geo.tol * longest           # drop noise slivers narrower than tol
    out, cross = out[wide], cross[wide]
    flip = cross @ geo.normal[i] < 0                                    # face patch i's way
    out[flip] = out[flip][:, ::-1]
    return out, len(parts), (tri.area - rest.area) * stretch


def split_contacts(scene, delta=None):
    """``scene`` with every patch split along its contact lines and the covered pieces dropped
    (module docstring), and a dict for the report: patches split, patches covered whole, covered
    pieces dropped, the triangles the split patches became, the covered area and delta.

    ``delta``: the coordinates' rounding (default :func:`rounding` of ``scene``'s; pass the file's
    for a subdivided scene, whose midpoints show more decimals than the file had)."""
    geo = _Geometry(scene, delta)
    replaced, info = {}, {"patches_split": 0, "patches_covered": 0, "covered_pieces": 0,
                          "triangles_from_split": 0, "covered_area": 0.0, "rounding": geo.delta}
    for plane in _planes(geo, scene.patches):
        covered = _covered_faces(plane, geo.tol)
        shapely.prepare(covered)
        for i in plane.members:
            got = _pieces(plane, geo, i, covered)
            if got is None:
                continue
            replaced[i], count, area = got
            info["patches_split" if len(replaced[i]) else "patches_covered"] += 1
            info["covered_pieces"] += count
            info["triangles_from_split"] += len(replaced[i])
            info["covered_area"] += float(area)
    return _rebuild(scene, replaced), info


def _rebuild(scene, replaced):
    """A Scene with patch i replaced by ``replaced[i]`` (corners (M, 3, 3)), in patch order; equal
    coordinates share one vertex so that subdivision splits shared edges alike."""
    if not replaced:
        return scene
    tris, parent = [], []
    for i in range(scene.patches):
        pieces = replaced.get(i, scene.patch_vertices[i][None])
        tris.append(pieces)
        parent += [i] * len(pieces)
    corners = np.concatenate(tris).reshape(-1, 3)
    if not len(corners):
        raise SceneError("every patch is covered by another face", path=scene.source or None)
    vertices, index = np.unique(corners, axis=0, return_inverse=True)
    parent = np.array(parent, dtype=np.int64)
    return Scene(name=scene.name, vertices=vertices, triangles=index.reshape(-1, 3).astype(np.int64),
                 reflectance=scene.reflectance[parent].copy(), emission=scene.emission[parent].copy(),
                 group=scene.group[parent].copy(), group_names=list(scene.group_names), camera=scene.camera,
                 source=scene.source)

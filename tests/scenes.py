"""Scenes and mesh builders the tests share (imported as ``scenes``; fixtures built from them are
in tests/conftest.py)."""

import itertools

import numpy as np

from blockray.host_driver.scene.builtin import CAMERAS, DEFAULT_MAX_EDGE, path
from blockray.host_driver.scene.objload import load_obj, subdivide
from blockray.host_driver.render.render import Visibility
from blockray.host_driver.scene.scene import Scene
from blockray.host_driver.traverse.voxel import VoxelGrid
from blockray.params import BoardParams
from blockray.samples import SampleScheme

#: the RTL back-ends' small machine: a 2 x 2 array, P = 2, B = 10 (tests/test_rtl_board.py)
RTL_PARAMS = BoardParams(rows=2, cols=2, boards=2, bits=10)
RTL_BITS = RTL_PARAMS.bits

#: the counters the RTL must reproduce exactly (ModelBoard.counters keys)
COUNTER_KEYS = ("board_cycles", "tests_issued", "tests_useful", "tests", "utilization",
                "board_cycles_per_board", "tests_issued_per_board", "tests_useful_per_board",
                "utilization_per_board", "load_cycles_per_board", "blocks", "rays", "bits")


def shooter_blocks(scene, board, shooters):
    """The block rays of ``shooters`` to every patch, on ``board`` prepared and loaded with the
    scene (4 samples, 3^3 voxels, the RTL machine's array)."""
    board.prepare(scene, SampleScheme(4))
    grid = VoxelGrid(scene.patch_vertices, 3, margin=board.margin)
    board.load(grid)
    vis = Visibility(scene, board, grid, SampleScheme(4), rows=RTL_PARAMS.rows, cols=RTL_PARAMS.cols)
    blocks = []
    for i in shooters:
        blocks += vis._blocks_for(i, np.arange(scene.patches))
    return blocks


def mesh_scene(vertices, triangles, name="t"):
    """A Scene of indexed ``triangles`` into ``vertices``, reflectance 0.5, nothing emitting."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    n = len(t)
    return Scene(name, v, t, np.full((n, 3), 0.5), np.zeros((n, 3)), np.zeros(n, dtype=np.int64))


def rectangle(origin, u, v, nu, nv):
    """Triangles (2 nu nv, 3, 3) of the parallelogram origin + [0,1] u + [0,1] v; normal along u x v."""
    origin, u, v = (np.asarray(x, dtype=np.float64) for x in (origin, u, v))
    a = np.arange(nu + 1) / nu
    b = np.arange(nv + 1) / nv
    P = origin + a[:, None, None] * u + b[None, :, None] * v
    tris = []
    for i in range(nu):
        for j in range(nv):
            tris.append([P[i, j], P[i + 1, j], P[i + 1, j + 1]])
            tris.append([P[i, j], P[i + 1, j + 1], P[i, j + 1]])
    return np.array(tris)


def make_scene(triangles, reflectance=0.5, emission=0.0, groups=None, name="test"):
    """A Scene from a triangle soup (M, 3, 3); reflectance/emission broadcast to (M, 3)."""
    T = np.asarray(triangles, dtype=np.float64)
    M = len(T)
    return Scene(name=name, vertices=T.reshape(-1, 3), triangles=np.arange(3 * M).reshape(M, 3),
                 reflectance=np.broadcast_to(np.asarray(reflectance, float), (M, 3)).copy(),
                 emission=np.broadcast_to(np.asarray(emission, float), (M, 3)).copy(),
                 group=np.zeros(M, dtype=np.int64) if groups is None else np.asarray(groups),
                 group_names=["all"])


def closed_box(n, size=1.0):
    """The six faces of a cube [0, size]^3, each n x n cells of 2 triangles, normals inward.
    Returns (triangles (12 n^2, 3, 3), face index per triangle)."""
    s = size
    X, Y, Z = np.eye(3) * s
    O = np.zeros(3)
    faces = [rectangle(O, X, Y, n, n),          # z = 0, normal +z
             rectangle(Z, Y, X, n, n),          # z = s, normal -z
             rectangle(O, Z, X, n, n),          # y = 0, normal +y
             rectangle(Y, X, Z, n, n),          # y = s, normal -y
             rectangle(O, Y, Z, n, n),          # x = 0, normal +x
             rectangle(X, Z, Y, n, n)]          # x = s, normal -x
    return np.concatenate(faces), np.repeat(np.arange(6), 2 * n * n)


def box_faces(lo, hi, inward):
    """Six quads of an axis-aligned box, oriented so normals point in (inward) or out."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c = (lo + hi) / 2
    faces = []
    for axis in range(3):
        for side in (lo, hi):
            u, w = [a for a in range(3) if a != axis]
            quad = []
            for du, dw in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = np.empty(3)
                p[axis] = side[axis]
                p[u] = (lo, hi)[du][u]
                p[w] = (lo, hi)[dw][w]
                quad.append(p)
            n = np.cross(quad[1] - quad[0], quad[2] - quad[0])
            towards_centre = np.dot(n, c - quad[0]) > 0
            if towards_centre != inward:
                quad = quad[::-1]
            faces.append(quad)
    return faces


def write_obj(tmp_path, objects, *, name="scene"):
    """objects: list of (group, material, faces); materials: dict name -> (Kd, Ke)."""
    lines, mtl, nv = [f"mtllib {name}.mtl"], [], 0
    mats = {}
    for group, (mat, kd, ke), faces in objects:
        mats[mat] = (kd, ke)
        lines += [f"o {group}", f"usemtl {mat}"]
        for quad in faces:
            for p in quad:
                lines.append("v " + " ".join(repr(float(x)) for x in p))
            lines.append("f " + " ".join(str(nv + k + 1) for k in range(len(quad))))
            nv += len(quad)
    for mat, (kd, ke) in mats.items():
        mtl += [f"newmtl {mat}", "Kd " + " ".join(map(str, kd)), "Ke " + " ".join(map(str, ke))]
    (tmp_path / f"{name}.mtl").write_text("\n".join(mtl) + "\n")
    path = tmp_path / f"{name}.obj"
    path.write_text("\n".join(lines) + "\n")
    return path


def room_obj(tmp_path):
    """A closed room with one emitting wall and a box that casts shadows: its OBJ file."""
    room = box_faces((0, 0, 0), (2, 2, 2), True)
    light, walls = room[3:4], room[:3] + room[4:]
    inner = box_faces((0.6, 0.0, 0.6), (1.4, 0.8, 1.4), False)
    return write_obj(tmp_path, [("walls", ("white", (0.5,) * 3, (0,) * 3), walls),
                                ("light", ("lamp", (0.5,) * 3, (1,) * 3), light),
                                ("block", ("white", (0.5,) * 3, (0,) * 3), inner)], name="room")


def room_scene(tmp_path, max_edge):
    return load_obj(room_obj(tmp_path), max_edge=max_edge)


def balance(scene, B):
    """absorbed / emitted - 1 per channel, from B, E, rho and A alone (not the code under test)."""
    rho, E, A = scene.reflectance, scene.emission, scene.areas
    H = (B - E) / rho
    return ((1 - rho) * H * A[:, None]).sum(axis=0) / (E * A[:, None]).sum(axis=0) - 1


# An open box: floor, two walls and a light under the top; a few patches, some occlusion.
BOX = """\
mtllib box.mtl
o floor
usemtl white
v 0 0 0
v 1 0 0
v 1 0 1
v 0 0 1
f 1 4 3 2
o left
usemtl red
v 0 0 0
v 0 1 0
v 0 1 1
v 0 0 1
f 5 8 7 6
o back
usemtl white
v 0 0 1
v 1 0 1
v 1 1 1
v 0 1 1
f 9 12 11 10
o blocker
usemtl white
v 0.3 0.4 0.3
v 0.7 0.4 0.3
v 0.7 0.4 0.7
v 0.3 0.4 0.7
f 13 14 15 16
o light
usemtl lamp
v 0.3 0.95 0.3
v 0.7 0.95 0.3
v 0.7 0.95 0.7
v 0.3 0.95 0.7
f 17 18 19 20
"""
BOX_MTL = """\
newmtl white
Kd 0.7 0.7 0.7
newmtl red
Kd 0.6 0.1 0.1
newmtl lamp
Kd 0.2 0.2 0.2
Ke 10 10 10
"""


def write(folder, obj, mtl=None, name="s", mtl_name=None):
    folder.mkdir(parents=True, exist_ok=True)
    if mtl is not None:
        (folder / (mtl_name or f"{name}.mtl")).write_text(mtl)
    path = folder / f"{name}.obj"
    path.write_text(obj)
    return path


# ---------------------------------------------------------------------------- closed scenes (energy balance)

def prism(footprint, height, bottom=False, open_side=None):
    """A closed prism standing on z = footprint's z: sides and top face outwards (counter-clockwise
    footprint seen from +z), bottom face optional, side ``open_side`` (a -> a+1) left out."""
    F = np.asarray(footprint, dtype=np.float64)
    up = np.array([0.0, 0.0, height])
    tris = []
    for k, (a, b) in enumerate(zip(F, np.roll(F, -1, axis=0))):
        if k != open_side:
            tris += [[a, b, b + up], [a, b + up, a + up]]
    tris += [[F[0] + up, F[k] + up, F[k + 1] + up] for k in range(1, len(F) - 1)]
    if bottom:
        tris += [[F[0], F[k + 1], F[k]] for k in range(1, len(F) - 1)]
    return np.array(tris)


def rect(x0, y0, x1, y1, z=0.0):
    return [(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)]


def box_with_block():
    """A closed box of 48 triangles with a closed cube of 12 triangles floating inside."""
    box, face = closed_box(2)
    cube, _ = closed_box(1, size=0.3)
    cube = cube[:, ::-1] + 0.35                                          # normals outward
    tris = np.concatenate([box, cube])
    E = np.zeros((len(tris), 3))
    E[:len(box)][face == 1] = [1.0, 2.0, 0.5]
    R = np.full((len(tris), 3), [0.5, 0.3, 0.7])
    R[len(box):] = [0.8, 0.6, 0.2]
    return make_scene(tris, reflectance=R, emission=E)


def closed_box_with_slab(n=3):
    """The unit cube (inward faces, n x n cells a face) with a 0.3 x 0.2 x 0.02 slab on its floor (low,
    so that it shadows little and the balance shows the covered part's loss, not the visibility's
    error), lit by the middle ceiling cell."""
    box, face = closed_box(n)
    slab = prism(rect(0.35, 0.4, 0.65, 0.6), 0.02)
    tris = np.concatenate([box, slab])
    E = np.zeros((len(tris), 3))
    ceiling = np.flatnonzero(face == 1)
    E[ceiling[len(ceiling) // 2 - 1:len(ceiling) // 2 + 1]] = [1.0, 2.0, 0.5]
    R = np.full((len(tris), 3), [0.5, 0.3, 0.7])
    R[len(box):] = [0.8, 0.6, 0.2]
    return make_scene(tris, reflectance=R, emission=E, name="closed box with slab")


def icosphere(levels, centre, radius):
    """Outward-facing icosphere of 20 * 4^levels triangles."""
    phi = (1 + 5 ** 0.5) / 2
    pts = np.array([p for s1 in (-1, 1) for s2 in (-1, 1)
                    for p in ((0, s1, s2 * phi), (s1, s2 * phi, 0), (s2 * phi, 0, s1))], float)
    faces = [f for f in itertools.combinations(range(12), 3)
             if all(abs(np.linalg.norm(pts[i] - pts[j]) - 2) < 1e-9 for i, j in itertools.combinations(f, 2))]
    tris = pts[np.array(faces)]
    for _ in range(levels):
        a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        tris = np.concatenate([np.stack(x, 1) for x in ([a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca])])
    tris = tris / np.linalg.norm(tris, axis=2, keepdims=True)
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    flip = (n * tris.mean(axis=1)).sum(axis=1) < 0
    tris[flip] = tris[flip][:, ::-1]
    return tris * radius + centre


def closed_scenes():
    """(name, scene) of the closed scenes whose energy balance the tests and
    benchmarks/bench_formfactor.py check."""
    rho = [0.5, 0.3, 0.7]
    box, face = closed_box(4)
    E = np.zeros((len(box), 3))
    E[0] = [1, 2, 0.5]
    yield "empty closed box (192 triangles, one emitting corner triangle)", make_scene(box, reflectance=rho, emission=E)
    sphere = icosphere(2, np.array([0.5, 0.45, 0.5]), 0.25)
    tris = np.concatenate([box, sphere])
    E = np.zeros((len(tris), 3))
    E[:len(box)][face == 1] = [1, 2, 0.5]
    R = np.full((len(tris), 3), rho)
    R[len(box):] = [0.8, 0.6, 0.2]
    yield (f"icosphere of {len(sphere)} triangles in a closed box ({len(tris)} triangles, lit ceiling)",
           make_scene(tris, reflectance=R, emission=E))
    yield "cornell closed (a front wall fitted to the opening, no floor under the blocks)", closed_cornell()


def closed_cornell(max_edge=None):
    """cornell closed patch by patch: its open side gets a wall fitted to the opening (the red wall
    is slanted, so the opening is a trapezoid, not the bounding box's face), and the floor leaves
    out the blocks' footprints (the published floor runs under the blocks, where a patch sees
    nothing). Triangulated with earcut, then subdivided like the built-in (``max_edge``, default
    the built-in's)."""
    import mapbox_earcut
    raw = load_obj(path("cornell"), name="cornell")
    V, T = raw.vertices, raw.triangles
    names = list(raw.group_names)
    floor = names.index("floor")
    keep = raw.group != floor
    on_floor = lambda g: np.unique(T[raw.group == names.index(g)].ravel())
    bottom = [v[np.abs(V[v, 1]) == 0] for v in (on_floor("short_block"), on_floor("tall_block"))]
    outline = np.unique(T[raw.group == floor].ravel())
    rings = [_ring(V[outline])] + [_ring(V[b]) for b in bottom]
    xz = np.concatenate(rings)[:, [0, 2]]
    tri = mapbox_earcut.triangulate_float64(xz, np.cumsum([len(r) for r in rings]).astype(np.uint32))
    floor_v = np.concatenate(rings)
    tri = tri.reshape(-1, 3)
    up = np.cross(floor_v[tri[:, 1]] - floor_v[tri[:, 0]], floor_v[tri[:, 2]] - floor_v[tri[:, 0]])[:, 1] > 0
    tri[~up] = tri[~up][:, ::-1]                          # the floor faces into the box (+y)
    front = np.array([[0, 0, 0], [V[:, 0][(V[:, 1] == 0) & (V[:, 2] == 0)].max(), 0, 0],
                      [V[:, 0][(V[:, 1] == V[:, 1].max()) & (V[:, 2] == 0)].max(), V[:, 1].max(), 0],
                      [0, V[:, 1].max(), 0]])
    front_tri = np.array([[0, 1, 2], [0, 2, 3]])          # facing +z, into the box
    k, m = len(V), len(floor_v)
    vertices = np.concatenate([V, floor_v, front])
    triangles = np.concatenate([T[keep], k + tri, k + m + front_tri])
    white = raw.reflectance[raw.group == floor][0]
    refl = np.concatenate([raw.reflectance[keep], np.repeat([white], len(tri) + 2, axis=0)])
    emis = np.concatenate([raw.emission[keep], np.zeros((len(tri) + 2, 3))])
    group = np.concatenate([raw.group[keep], np.full(len(tri), floor), np.full(2, len(names))])
    closed = Scene(name="cornell-closed", vertices=vertices, triangles=triangles, reflectance=refl,
                   emission=emis, group=group, group_names=names + ["front wall"],
                   camera=CAMERAS["cornell"], source="builtin:cornell, closed")
    return subdivide(closed, DEFAULT_MAX_EDGE["cornell"] if max_edge is None else max_edge)


def _ring(points):
    """The corners of a convex polygon on the floor, in order round its centre (x, z plane)."""
    c = points.mean(axis=0)
    return points[np.argsort(np.arctan2(points[:, 2] - c[2], points[:, 0] - c[0]))]


def two_walls_and_blocker():
    """Two walls of 8 triangles (2 x 2 units) facing each other 6 apart, the far one emitting, and a
    square blocker between them: far enough apart for cluster links (hierarchical clustering), few
    enough rays for the RTL boards; every coordinate dyadic."""
    x, y, z = np.eye(3)
    def grid(origin, u, v):
        cells = [origin + i * u + j * v for i in range(2) for j in range(2)]
        return np.array([t for o in cells for t in ([o, o + u, o + u + v], [o, o + u + v, o + v])])
    blocker = rectangle(np.array([3.0, 0.5, 0.375]), z * 0.75, y * 0.875, 1, 1)
    tris = np.concatenate([grid(np.zeros(3), y, z), grid(6.0 * x, z, y), blocker])
    emission = np.zeros((len(tris), 3))
    emission[8:16] = 1.0
    return make_scene(tris, emission=emission)

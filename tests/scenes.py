"""Scenes and mesh builders the tests share (imported as ``scenes``; fixtures built from them are
in tests/conftest.py)."""

import numpy as np

from blockray.host_driver.objload import load_obj
from blockray.host_driver.scene import Scene
from blockray.params import BoardParams

#: the RTL back-ends' small machine: a 2 x 2 array, P = 2, B = 10 (tests/test_rtl_board.py)
RTL_PARAMS = BoardParams(rows=2, cols=2, boards=2)
RTL_BITS = 10


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

"""Furnace tests (issue 34): closed convex enclosures in which every face emits E = 1 with
reflectance rho = 0.5. The row sums of an enclosure's exact factors are 1, so every patch has
B = E / (1 - rho) = 2 exactly; any wrong pair factor shows as a patch away from 2.

The enclosures are written as a modelling tool writes them: cubes at several grids, rotated,
translated, of non-dyadic sizes, their coordinates rounded to 6 and to 9 decimals, and geodesic
spheres (subdivided icosahedra). No occluder: the exact unoccluded factors are the visible ones.
"""

import math

import numpy as np
import pytest

from blockray.host_driver.radiosity.formfactor import form_factor_matrix
from scenes import closed_box, make_scene

RHO, E = 0.5, 1.0


def _rotation(seed):
    """A seeded random rotation (QR of a Gaussian matrix)."""
    Q, R = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    Q = Q * np.sign(np.diag(R))
    return Q if np.linalg.det(Q) > 0 else -Q


def geodesic_sphere(levels, radius):
    """An icosahedron split ``levels`` times (each triangle in 4, midpoints pushed to the sphere),
    normals inward: a convex enclosure of 20 * 4^levels triangles."""
    t = (1 + math.sqrt(5)) / 2
    V = [np.array(v, float) for v in [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
                                      (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]]
    F = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6),
         (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10),
         (8, 6, 7), (9, 8, 1)]
    tris = [np.array([V[a], V[b], V[c]]) for a, b, c in F]
    for _ in range(levels):
        out = []
        for a, b, c in tris:
            ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
            out += [np.array(x) for x in ([a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca])]
        tris = out
    T = np.array([[v / np.linalg.norm(v) * radius for v in tri] for tri in tris])
    return inward(T)


def inward(T):
    """Each triangle wound so that its normal points to the enclosure's centre."""
    centre = T.reshape(-1, 3).mean(axis=0)
    n = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    out = np.einsum("ij,ij->i", n, centre - T.mean(axis=1)) > 0
    return np.where(out[:, None, None], T, T[:, ::-1])


def furnace(T):
    """B of every patch of the enclosure T with E = 1, rho = 0.5 everywhere, solved directly."""
    scene = make_scene(T, reflectance=RHO, emission=E)
    F = form_factor_matrix(scene)
    B = np.linalg.solve(np.eye(len(T)) - RHO * F, np.full(len(T), E))
    return B, F.sum(axis=1)


ENCLOSURES = {
    "cube 3, 9 decimals": lambda: np.round(closed_box(3, 1.0)[0] * 1.0, 9),
    "cube 6 of 1/6, 9 decimals": lambda: np.round(closed_box(6, 1.0)[0], 9),
    "cube 4, rotated, 6 decimals": lambda: np.round(closed_box(4, 0.7318)[0] @ _rotation(5).T + [0.123, -4.5, 2.0], 6),
    "cube 4, rotated, 9 decimals": lambda: np.round(closed_box(4, 13.37)[0] @ _rotation(6).T + [31.1, 0.7, -8.0], 9),
    "cube 5, rotated, tiny, 9 decimals": lambda: np.round(closed_box(5, 0.0371)[0] @ _rotation(7).T, 9),
    "geodesic sphere 80, rotated, 6 decimals": lambda: inward(np.round(geodesic_sphere(1, 1.7) @ _rotation(8).T, 6)),
    "geodesic sphere 320, 9 decimals": lambda: inward(np.round(geodesic_sphere(2, 0.3) + [1.1, 2.2, 3.3], 9)),
}


@pytest.mark.parametrize("name", list(ENCLOSURES))
def test_every_patch_of_an_emitting_enclosure_reaches_E_over_1_minus_rho(name):
    B, rows = furnace(ENCLOSURES[name]())
    print(f"{name}: {len(B)} patches, max |B - 2| {np.abs(B - 2).max():.2e}, max |row sum - 1| "
          f"{np.abs(rows - 1).max():.2e}")
    assert np.isfinite(B).all()
    assert np.abs(B - E / (1 - RHO)).max() < 1e-6
    # each pair is held to FAR_TARGET (1e-6) relative, each of its edge pairs to a tenth of it
    assert np.abs(rows - 1).max() < 1e-7


def write_obj(path, T, decimals):
    """T as an OBJ (vertices printed to ``decimals``) with one material Kd 0.5, Ke 1."""
    mtl = path.with_suffix(".mtl")
    mtl.write_text(f"newmtl wall\nKd {RHO} {RHO} {RHO}\nKe {E} {E} {E}\n")
    lines = [f"mtllib {mtl.name}", "usemtl wall"]
    lines += [f"v {x:.{decimals}f} {y:.{decimals}f} {z:.{decimals}f}" for x, y, z in T.reshape(-1, 3)]
    lines += [f"f {3 * k + 1} {3 * k + 2} {3 * k + 3}" for k in range(len(T))]
    path.write_text("\n".join(lines) + "\n")


def test_the_issue_cube_renders_B_2_through_the_golden_board(tmp_path):
    """The issue's cube: 6 x 6 per face, vertices at multiples of 1/6 written as 0.166666667,
    rendered by the CLI with the golden board (rays included): B = 2 within 1e-6, exit 0."""
    from blockray.host_driver.cli import main
    obj = tmp_path / "cube.obj"
    write_obj(obj, closed_box(6, 1.0)[0], 9)
    csv = tmp_path / "cube.csv"
    assert main(["render", str(obj), "--board", "golden", "--solver", "jacobi", "--tolerance", "1e-10",
                 "--patches", str(csv), "--quiet"]) == 0
    B = np.loadtxt(csv, delimiter=",", skiprows=1, usecols=(6, 7, 8))
    print(f"cube.obj: {len(B)} patches, max |B - 2| {np.abs(B - 2).max():.2e}")
    assert len(B) == 432 and np.abs(B - 2).max() < 1e-6

"""OBJ/MTL loading, bad-input errors, subdivision and the built-in scenes."""

import importlib.util
import math
import warnings
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from blockray.errors import ParameterError, SceneError
from blockray.host_driver.scene import builtin
from blockray.host_driver.scene.objload import (DEFAULT_REFLECTANCE, SceneWarning, load_obj, subdivide)
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.scene.scene import Scene

MTL = """\
newmtl white
Kd 0.5 0.5 0.5
newmtl lamp
Kd 0.1 0.2 0.3
Ke 4 5 6
newmtl plain
Ns 10
"""


def write(tmp_path, obj, mtl=None, name="s.obj"):
    if mtl is not None:
        (tmp_path / "s.mtl").write_text(mtl)
    path = tmp_path / name
    path.write_text(obj)
    return path


def polygon_area(points):
    """Area of a planar polygon (shoelace on the xy plane; points have z = 0)."""
    x, y = np.asarray(points, dtype=float)[:, 0], np.asarray(points, dtype=float)[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


# ---- loading -----------------------------------------------------------------------------------

def test_quads_polygons_groups_materials(tmp_path):
    path = write(tmp_path, """\
mtllib s.mtl
# a unit square quad in group "floor", white
o floor
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
usemtl white
f 1 2 3 4
g lamp shade
usemtl lamp
v 0 0 1
v 2 0 1
v 3 1 1
v 1 2 1
v -1 1 1
vt 0 0
vn 0 0 1
f -5/1/1 -4/1/1 -3/1/1 -2/1/1 -1/1/1
usemtl plain
f 1//1 2//1 5//1
""", MTL)
    s = load_obj(path)
    assert s.name == "s" and s.source == str(path)
    assert s.patches == 2 + 3 + 1
    assert s.group_names == ["floor", "lamp shade"]
    np.testing.assert_array_equal(s.group, [0, 0, 1, 1, 1, 1])
    np.testing.assert_allclose(s.reflectance[:2], 0.5)
    np.testing.assert_allclose(s.reflectance[2:5], [[0.1, 0.2, 0.3]] * 3)
    np.testing.assert_allclose(s.emission[2:5], [[4, 5, 6]] * 3)
    np.testing.assert_allclose(s.emission[[0, 1, 5]], 0)
    np.testing.assert_allclose(s.reflectance[5], DEFAULT_REFLECTANCE)   # material without Kd
    # Areas: the unit square, the pentagon (shoelace) and the last triangle.
    pent = [(0, 0), (2, 0), (3, 1), (1, 2), (-1, 1)]
    assert s.areas[:2].sum() == pytest.approx(1.0)
    assert s.areas[2:5].sum() == pytest.approx(polygon_area(pent))
    assert s.areas[5] == pytest.approx(0.5)
    # Normals follow the corner order (counter-clockwise seen from +z -> +z).
    np.testing.assert_allclose(s.normals[:5], [[0, 0, 1]] * 5, atol=1e-12)
    np.testing.assert_allclose(s.normals[5], [0, -1, 0], atol=1e-12)


def test_faces_before_usemtl_and_groups_get_defaults(tmp_path):
    s = load_obj(write(tmp_path, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"), name="x")
    assert s.name == "x" and s.group_names == ["default"]
    np.testing.assert_allclose(s.reflectance, [DEFAULT_REFLECTANCE])
    np.testing.assert_allclose(s.emission, 0)


def test_concave_polygon_is_ear_clipped(tmp_path):
    # An L shape, listed from a reflex corner so a fan from corner 1 would leave the polygon.
    pts = [(1, 1), (1, 2), (0, 2), (0, 0), (2, 0), (2, 1)]
    obj = "".join(f"v {x} {y} 0\n" for x, y in pts) + "f 1 2 3 4 5 6\n"
    s = load_obj(write(tmp_path, obj))
    assert s.patches == 4
    assert s.areas.sum() == pytest.approx(polygon_area(pts)) == pytest.approx(3.0)
    np.testing.assert_allclose(s.normals, [[0, 0, 1]] * 4, atol=1e-12)  # no folded triangles


def test_non_planar_quad_becomes_two_triangles(tmp_path):
    s = load_obj(write(tmp_path, "v 0 0 0\nv 1 0 0\nv 1 1 0.3\nv 0 1 0\nf 1 2 3 4\n"))
    assert s.patches == 2
    assert not np.allclose(s.normals[0], s.normals[1])


def test_coincident_vertices_are_merged(tmp_path):
    # Two triangles that repeat the shared corners instead of sharing indices.
    obj = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv -0 5 5\nf 1 2 3\nf 4 5 6\n"
    s = load_obj(write(tmp_path, obj))
    assert len(s.vertices) == 4                         # merged, unused vertex dropped
    assert len({tuple(sorted(e)) for t in s.triangles
                for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}) == 5


# ---- bad input ---------------------------------------------------------------------------------

GOOD_TRI = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"

# (OBJ text, MTL text or None, file the error names, line, words the message must contain)
BAD = {
    "v_too_few":      (GOOD_TRI + "v 1 2\nf 1 2 3\n", None, "obj", 4, "3 or 4 or 6 numbers"),
    "v_not_number":   (GOOD_TRI + "v 1 x 3\n", None, "obj", 4, "not a number"),
    "v_nan":          (GOOD_TRI + "v nan 0 0\n", None, "obj", 4, "not a number: 'nan'"),
    "v_inf":          ("v 0 0 0\nv 1 -inf 0\n", None, "obj", 2, "not a number: '-inf'"),
    "f_out_of_range": (GOOD_TRI + "f 1 2 4\n", None, "obj", 4, "out of range"),
    "f_zero_index":   (GOOD_TRI + "f 0 1 2\n", None, "obj", 4, "out of range"),
    "f_negative_oor": (GOOD_TRI + "f -1 -2 -4\n", None, "obj", 4, "out of range"),
    "f_bad_token":    (GOOD_TRI + "f 1 2 three\n", None, "obj", 4, "bad vertex index"),
    "f_two_corners":  (GOOD_TRI + "f 1 2\n", None, "obj", 4, "at least 3"),
    "f_vt_oor":       (GOOD_TRI + "vt 0 0\nf 1/1 2/2 3/1\n", None, "obj", 5, "texture coordinate"),
    "unknown_stmt":   (GOOD_TRI + "fx 1 2 3\n", None, "obj", 4, "unknown statement"),
    "unknown_mtl":    ("mtllib s.mtl\n" + GOOD_TRI + "usemtl nope\nf 1 2 3\n", MTL, "obj", 5,
                       "unknown material 'nope'"),
    "missing_mtl":    ("mtllib other.mtl\n" + GOOD_TRI + "f 1 2 3\n", None, "obj", 1, "other.mtl"),
    "kd_one":         ("mtllib s.mtl\n" + GOOD_TRI, "newmtl a\nKd 0.2 0.2 0.2\nnewmtl red\nKd 1 0 0\n",
                       "mtl", 4, "'red'"),
    "kd_negative":    ("mtllib s.mtl\n" + GOOD_TRI, "newmtl m\n\nKd -0.1 0 0\n", "mtl", 3, "'m'"),
    "kd_nan":         ("mtllib s.mtl\n" + GOOD_TRI, "newmtl m\nKd 0.1 nan 0\n", "mtl", 2, "not a number"),
    "kd_count":       ("mtllib s.mtl\n" + GOOD_TRI, "newmtl m\nKd 0.1 0.2\n", "mtl", 2, "1 or 3"),
    "kd_text":        ("mtllib s.mtl\n" + GOOD_TRI, "newmtl m\nKd red\n", "mtl", 2, "not a number"),
    "ke_negative":    ("mtllib s.mtl\n" + GOOD_TRI, "newmtl m\nKe 1 -1 0\n", "mtl", 2, "emission"),
    "ke_nan":         ("mtllib s.mtl\n" + GOOD_TRI, "newmtl m\nKe nan\n", "mtl", 2, "not a number"),
    "kd_before_new":  ("mtllib s.mtl\n" + GOOD_TRI, "Kd 0.1 0.1 0.1\n", "mtl", 1, "newmtl"),
    "empty":          (GOOD_TRI, None, "obj", None, "no triangles"),
    "only_zero_area": ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", None, "obj", None, "no triangles"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_names_file_and_line(tmp_path, case):
    obj, mtl, where, line, words = BAD[case]
    path = write(tmp_path, obj, mtl)
    named = path if where == "obj" else tmp_path / "s.mtl"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SceneWarning)
        with pytest.raises(SceneError) as info:
            load_obj(path)
    err = info.value
    assert str(err.path) == str(named)
    assert err.line == line
    prefix = f"{named}:{line}: " if line is not None else f"{named}: "
    assert str(err).startswith(prefix), str(err)
    assert words in str(err), str(err)


def test_unreadable_file(tmp_path):
    with pytest.raises(SceneError) as info:
        load_obj(tmp_path / "missing.obj")
    assert str(info.value).startswith(f"{tmp_path / 'missing.obj'}: ")
    with pytest.raises(SceneError, match="missing.obj"):
        load_scene(str(tmp_path / "missing.obj"))


def test_zero_area_triangles_are_dropped_and_counted(tmp_path):
    obj = GOOD_TRI + "v 2 0 0\nv 0 0 0\n" + "f 1 2 3\nf 1 2 4\nf 1 1 3\nf 2 3 1\nf 5 2 4\n"
    with pytest.warns(SceneWarning, match="dropped 3 zero-area triangles"):
        s = load_obj(write(tmp_path, obj))
    assert s.patches == 2
    np.testing.assert_allclose(s.areas, [0.5, 0.5])


# ---- subdivision -------------------------------------------------------------------------------

def edge_counts(triangles):
    """Counter of undirected edges, and Counter of directed edges."""
    undirected, directed = Counter(), Counter()
    for t in triangles:
        for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])):
            undirected[(min(a, b), max(a, b))] += 1
            directed[(a, b)] += 1
    return undirected, directed


def closed_mesh(rng):
    """A closed, consistently oriented mesh: a random box (12 triangles) in one group and a
    tetrahedron in another, with random vertex order."""
    size = rng.uniform(0.5, 3.0, 3)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)]) * size
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [(a, b, c) for a, b, c, d in quads] + [(a, c, d) for a, b, c, d in quads]
    tet = rng.normal(size=(4, 3)) + [5, 0, 0]
    t = [(0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2)]
    if np.dot(np.cross(tet[1] - tet[0], tet[2] - tet[0]), tet[3] - tet[0]) > 0:
        t = [(a, c, b) for a, b, c in t]
    tris += [(a + 8, b + 8, c + 8) for a, b, c in t]
    vertices = np.vstack([corners, tet])
    n = len(tris)
    return Scene(name="closed", vertices=vertices, triangles=np.array(tris),
                 reflectance=np.full((n, 3), 0.5), emission=np.zeros((n, 3)),
                 group=np.array([0] * 12 + [1] * 4), group_names=["box", "tet"])


@pytest.mark.parametrize("seed", range(4))
def test_subdivide_closed_mesh(seed):
    rng = np.random.default_rng(seed)
    print(f"seed={seed}")
    scene = closed_mesh(rng)
    _, directed = edge_counts(scene.triangles)
    assert set(directed.values()) == {1}                 # the input is a closed oriented mesh
    max_edge = rng.uniform(0.15, 0.6)
    out = subdivide(scene, max_edge)
    v = out.patch_vertices
    lengths = np.linalg.norm(v - np.roll(v, -1, axis=1), axis=2)
    assert lengths.max() <= max_edge
    assert out.patches > 10 * scene.patches
    # Area preserved overall and per group.
    for g in (0, 1):
        assert out.areas[out.group == g].sum() == pytest.approx(scene.areas[scene.group == g].sum())
    # Crack-free, no T-junctions: every edge is shared by exactly two triangles, in opposite
    # directions (which also proves every child kept its parent's orientation).
    undirected, directed = edge_counts(out.triangles)
    assert set(undirected.values()) == {2}
    assert set(directed.values()) == {1}
    # Children keep the parent's normal.
    for g in (0, 1):
        mask = out.group == g
        # every child normal equals the normal of some parent triangle of its group
        parents = scene.normals[scene.group == g]
        best = (out.normals[mask] @ parents.T).max(axis=1)
        np.testing.assert_allclose(best, 1.0, atol=1e-9)


def test_subdivide_keeps_attributes_and_camera():
    s = builtin.load("cornell", max_edge=1e9)
    out = subdivide(s, 150.0)
    assert out.camera == s.camera and out.source == s.source and out.group_names == s.group_names
    for g in range(len(s.group_names)):
        assert out.areas[out.group == g].sum() == pytest.approx(s.areas[s.group == g].sum())
        assert {tuple(r) for r in out.reflectance[out.group == g]} == \
               {tuple(r) for r in s.reflectance[s.group == g]}
    assert out.emission.sum(axis=0) @ [1, 1, 1] > 0


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), "abc"])
def test_subdivide_rejects_bad_max_edge(bad):
    s = builtin.load("cornell", max_edge=1e9)
    with pytest.raises(ParameterError, match="^max_edge must be a positive number"):
        subdivide(s, bad)
    with pytest.raises(ParameterError, match="^max_edge must be a positive number"):
        load_scene("cornell", max_edge=bad)


# ---- built-in scenes ---------------------------------------------------------------------------

CORNELL_CENTRE = np.array([278.0, 274.4, 279.6])


def groups(scene, *names):
    return np.isin(scene.group, [scene.group_names.index(n) for n in names])


def test_cornell_loads_with_published_camera():
    s = load_scene("cornell")
    assert 600 <= s.patches <= 1500
    assert s.source == "builtin:cornell"
    assert s.camera.position == (278.0, 273.0, -800.0)
    assert np.allclose(np.subtract(s.camera.look_at, s.camera.position) @ [0, 0, 1],
                       np.linalg.norm(np.subtract(s.camera.look_at, s.camera.position)))
    assert s.camera.fov == pytest.approx(39.3, abs=0.05)
    assert set(s.group_names) == {"floor", "ceiling", "light", "back_wall", "red_wall",
                                  "green_wall", "short_block", "tall_block"}
    assert ((s.reflectance >= 0) & (s.reflectance < 1)).all()
    # Only the light emits, the red wall is red and the green wall green.
    assert (s.emission.max(axis=1) > 0).tolist() == groups(s, "light").tolist()
    assert (s.reflectance[groups(s, "red_wall")] == [0.65, 0.05, 0.05]).all()
    assert (s.reflectance[groups(s, "green_wall")] == [0.12, 0.45, 0.15]).all()
    # --max-edge overrides the default subdivision; the file's 46 triangles, or 58 with the floor's
    # two cut round the blocks' footprints (host_driver/scene/contact.py)
    assert load_scene("cornell", max_edge=1e9, contact=False).patches == 46
    assert load_scene("cornell", max_edge=1e9).patches == 58


def test_cornell_normals_face_into_the_box():
    s = load_scene("cornell")
    walls = groups(s, "floor", "ceiling", "light", "back_wall", "red_wall", "green_wall")
    to_centre = CORNELL_CENTRE - s.centroids[walls]
    assert (np.sum(s.normals[walls] * to_centre, axis=1) > 0).all()
    np.testing.assert_allclose(s.normals[groups(s, "light")], [[0, -1, 0]] * groups(s, "light").sum(),
                               atol=1e-12)
    # Blocks face outwards: away from their vertical axis at mid height.
    for name in ("short_block", "tall_block"):
        m = groups(s, name)
        centre = s.centroids[m].mean(axis=0)
        centre[1] = s.patch_vertices[m][:, :, 1].max() / 2
        assert (np.sum(s.normals[m] * (s.centroids[m] - centre), axis=1) > 0).all()


def test_cornell_red_wall_is_not_planar_and_published_corners():
    s = load_scene("cornell", max_edge=1e9)
    red = groups(s, "red_wall")
    assert red.sum() == 2
    assert not np.allclose(s.normals[red][0], s.normals[red][1])
    corners = {tuple(p) for p in s.patch_vertices[red].reshape(-1, 3)}
    assert corners == {(552.8, 0, 0), (549.6, 0, 559.2), (556.0, 548.8, 559.2), (556.0, 548.8, 0)}


def test_cornell_light_does_not_overlap_the_ceiling():
    s = load_scene("cornell")
    light, ceiling = groups(s, "light"), groups(s, "ceiling")
    # Both lie in the ceiling plane ...
    assert np.all(s.patch_vertices[light | ceiling][:, :, 1] == 548.8)
    assert s.areas[light].sum() == pytest.approx(130 * 105)
    # ... and tile the published ceiling rectangle without overlap.
    assert s.areas[light].sum() + s.areas[ceiling].sum() == pytest.approx(556.0 * 559.2)
    # No ceiling triangle covers a point of the light (test a grid of points strictly inside).
    xs, zs = np.meshgrid(np.linspace(214, 342, 17), np.linspace(228, 331, 17))
    pts = np.stack([xs.ravel(), zs.ravel()], axis=1)
    tri = s.patch_vertices[ceiling][:, :, [0, 2]]
    a, b, c = tri[:, None, 0], tri[:, None, 1], tri[:, None, 2]

    def side(p, q, r):
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - \
               (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])
    p = pts[None]
    d1, d2, d3 = side(a, b, p), side(b, c, p), side(c, a, p)
    inside = ((d1 > 0) & (d2 > 0) & (d3 > 0)) | ((d1 < 0) & (d2 < 0) & (d3 < 0))
    assert not inside.any()


def test_room_loads():
    s = load_scene("room")
    # the paper's room has 3013 patches; cutting round the furniture's footprints adds about 20%
    assert 2500 <= load_scene("room", contact=False).patches <= 3500 < s.patches <= 4000
    assert s.source == "builtin:room" and s.camera is not None
    assert ((s.reflectance >= 0) & (s.reflectance < 1)).all()
    lo, hi = s.bbox
    inside_camera = np.all((np.array(s.camera.position) > lo) & (np.array(s.camera.position) < hi))
    assert inside_camera
    # White ceiling light facing down; six yellow up-lights whose lit faces face up.
    ceiling_light = groups(s, "ceiling_light")
    e = s.emission[ceiling_light]
    assert (e > 0).all() and np.allclose(e, e[:, :1])
    np.testing.assert_allclose(s.normals[ceiling_light], [[0, -1, 0]] * ceiling_light.sum(), atol=1e-12)
    up = [n for n in s.group_names if n.startswith("uplight")]
    assert len(up) == 6
    lit = (s.emission.max(axis=1) > 0) & groups(s, *up)
    assert {int(s.group[i]) for i in np.flatnonzero(lit)} == {s.group_names.index(n) for n in up}
    np.testing.assert_allclose(s.normals[lit], [[0, 1, 0]] * lit.sum(), atol=1e-12)
    assert (s.emission[lit][:, 0] > 2 * s.emission[lit][:, 2]).all()    # yellow: R >> B
    # Furniture that casts shadows.
    for name in ("table", "chair_0", "bookshelf", "sofa"):
        assert name in s.group_names


def test_room_walls_face_inwards_and_furniture_outwards():
    s = load_scene("room")
    lo, hi = s.bbox
    centre = (lo + hi) / 2
    shell = groups(s, "floor", "ceiling", "ceiling_light", "front_wall", "back_wall",
                   "left_wall", "right_wall")
    assert (np.sum(s.normals[shell] * (centre - s.centroids[shell]), axis=1) > 0).all()
    # Furniture: no face lying on the floor faces down, no face touching a wall faces into it.
    furniture = ~shell
    n, c = s.normals[furniture], s.centroids[furniture]
    assert not ((c[:, 1] < 1e-9) & (n[:, 1] < -0.5)).any()
    # Faces touching a wall must not point into it.
    for axis, value, sign in ((0, lo[0], -1), (0, hi[0], 1), (2, lo[2], -1), (2, hi[2], 1)):
        touching = np.abs(c[:, axis] - value) < 1e-9
        assert not (touching & (n[:, axis] * sign > 0.5)).any()


def test_load_scene_path_and_unknown_name(tmp_path):
    path = write(tmp_path, GOOD_TRI + "f 1 2 3\n")
    assert load_scene(str(path)).patches == 1
    assert load_scene(str(path), max_edge=0.25).patches > 1
    with pytest.raises(SceneError, match="built-in"):
        load_scene("no-such-scene")


SCENES = Path(__file__).resolve().parents[1] / "host_driver" / "scene" / "scenes"   # the source tree


def make_scenes_module():
    spec = importlib.util.spec_from_file_location("make_scenes", SCENES / "make_scenes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_generated_files_are_up_to_date(tmp_path, monkeypatch):
    """The committed OBJ/MTL files are what make_scenes.py generates."""
    module = make_scenes_module()
    monkeypatch.setattr(module, "HERE", tmp_path)
    module.cornell()
    module.room()
    for name in ("cornell.obj", "cornell.mtl", "room.obj", "room.mtl"):
        assert (tmp_path / name).read_text() == (SCENES / name).read_text()
        assert (tmp_path / name).read_text() == (builtin.path("room").parent / name).read_text()


def test_camera_fov_matches_published_film():
    assert builtin.CAMERAS["cornell"].fov == pytest.approx(math.degrees(2 * math.atan(12.5 / 35)))


def test_generator_boxes_face_outwards():
    """Furniture in ``room`` is built from ObjWriter.box: every face must point outwards."""
    w = make_scenes_module().ObjWriter("t")
    lo, hi = np.array([0.5, -1.0, 2.0]), np.array([1.5, 3.0, 2.5])
    w.box("b", "m", tuple(lo), tuple(hi), skip=("-y",))
    faces = w.groups["b"]
    assert len(faces) == 5
    for _, poly in faces:
        p = np.array(poly)
        normal = np.cross(p[1] - p[0], p[2] - p[0])
        assert np.dot(normal, p.mean(axis=0) - (lo + hi) / 2) > 0

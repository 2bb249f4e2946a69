"""The rasteriser against an independent per-pixel ray cast, Gouraud shading, tone map, PNG."""

import math

import numpy as np
import pytest
from PIL import Image

from blockray.errors import ParameterError
from blockray.host_driver.render.image import render_image, save_png, vertex_radiosity
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.scene.scene import Camera

from scenes import make_scene

W = H = 64
CAMERA = Camera(position=(0.0, 0.0, 0.0), look_at=(0.0, 0.0, 1.0), up=(0.0, 1.0, 0.0), fov=90.0)


def quad(a, b, c, d):
    return [(a, b, c), (a, c, d)]


def raycast(camera, width, height, triangles):
    """Per pixel: index of the nearest triangle hit by the ray through the pixel centre, or -1.

    Written from the camera definition alone (right = forward x up, y down, vertical fov),
    with Moller-Trumbore intersection; it shares no code with the rasteriser.
    """
    pos = np.array(camera.position, dtype=float)
    fwd = np.array(camera.look_at, dtype=float) - pos
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, camera.up)
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    t = math.tan(math.radians(camera.fov) / 2)
    j, i = np.mgrid[0:height, 0:width]
    u = (i + 0.5 - width / 2) / (height / 2) * t
    v = (height / 2 - (j + 0.5)) / (height / 2) * t
    d = fwd + u[..., None] * right + v[..., None] * up                    # (H, W, 3)
    best = np.full((height, width), np.inf)
    hit = np.full((height, width), -1)
    for k, (a, b, c) in enumerate(np.asarray(triangles, dtype=float)):
        e1, e2 = b - a, c - a
        p = np.cross(d, e2)
        det = p @ e1
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = pos - a
            bu = (p @ s) * inv
            q = np.cross(s, e1)
            bv = (d @ q) * inv
            dist = (q @ e2) * inv
        ok = (det != 0) & (bu >= 0) & (bv >= 0) & (bu + bv <= 1) & (dist > 0) & (dist < best)
        best[ok] = dist[ok]
        hit[ok] = k
    return hit


def test_emissive_quad_footprint_matches_ray_cast():
    # At z = 2 with a 90 degree fov, 1 world unit = 16 pixels: the edges x = -0.75, 0.5 and
    # y = -1, 0.25 fall on pixel borders, never through a pixel centre.
    tris = quad((-0.75, -1.0, 2.0), (0.5, -1.0, 2.0), (0.5, 0.25, 2.0), (-0.75, 0.25, 2.0))
    img = render_image(make_scene(tris, emission=1.0), np.ones((2, 3)), width=W, height=H, camera=CAMERA)
    assert img.shape == (H, W, 3) and img.dtype == np.uint8
    expected = raycast(CAMERA, W, H, tris) >= 0
    assert expected.sum() == 20 * 20
    # Independently: right = forward x up = -x, so world x in [-0.75, 0.5] is columns 24..43.
    cols = np.flatnonzero(expected.any(axis=0))
    rows = np.flatnonzero(expected.any(axis=1))
    assert (cols.min(), cols.max(), rows.min(), rows.max()) == (24, 43, 28, 47)
    assert (img[expected] == 255).all()
    assert (img[~expected] == 0).all()


@pytest.mark.parametrize("seed", range(3))
def test_random_triangles_depth_order_matches_ray_cast(seed):
    rng = np.random.default_rng(seed)
    print(f"seed={seed}")
    n = 16
    centres = rng.uniform([-1.5, -1.5, 2.0], [1.5, 1.5, 5.0], (n, 3))
    tris = centres[:, None, :] + rng.normal(scale=1.5, size=(n, 3, 3))
    tris[:, :, 2] = np.maximum(tris[:, :, 2], 0.5)              # in front of the camera
    # Distinct grey levels identify the triangle in the image (tone map disabled: exposure 1).
    level = (np.arange(n) + 1) / (n + 1)
    radiosity = np.repeat(level[:, None], 3, axis=1) ** 2.2
    scene = make_scene(tris, emission=radiosity)
    group = np.arange(n)                                         # no smoothing across triangles
    scene.group = group
    img = render_image(scene, radiosity, width=W, height=H, camera=CAMERA, exposure=1.0)
    hit = raycast(CAMERA, W, H, tris)
    expected = np.where(hit >= 0, np.round(255 * level[hit]), 0)
    diff = np.abs(img[:, :, 0].astype(int) - expected)
    # Pixel centres within rounding distance of an edge may differ; allow at most a handful.
    assert (diff > 1).sum() <= 3, np.argwhere(diff > 1)
    assert (hit >= 0).sum() > 0.3 * W * H
    # Depth order mattered: many pixels are covered by more than one triangle.
    covered = sum((raycast(CAMERA, W, H, tris[k:k + 1]) >= 0).astype(int) for k in range(n))
    assert (covered > 1).sum() > 0.05 * W * H


def test_back_faces_are_drawn_and_nearer_wins():
    front = quad((-1, -1, 2), (-1, 1, 2), (1, 1, 2), (1, -1, 2))          # faces the camera
    back = quad((-3, -3, 4), (3, -3, 4), (3, 3, 4), (-3, 3, 4))
    tris = front + back
    scene = make_scene(tris, emission=[[1, 0, 0]] * 2 + [[0, 1, 0]] * 2)
    scene.group = np.array([0, 0, 1, 1])
    radiosity = scene.emission
    assert scene.normals[0] @ [0, 0, -1] > 0 > scene.normals[2] @ [0, 0, -1]  # far one faces away
    for order in ([0, 1, 2, 3], [2, 3, 0, 1]):
        s = make_scene(np.array(tris)[order], emission=radiosity[order])
        s.group = scene.group[order]
        img = render_image(s, radiosity[order], width=W, height=H, camera=CAMERA, exposure=1.0)
        assert tuple(img[32, 32]) == (255, 0, 0)        # the near quad hides the far one
        assert tuple(img[32, 8]) == (0, 255, 0)         # only the far quad there
        assert tuple(img[0, 0]) == (0, 0, 0)


def test_near_plane_clipping_floor_behind_camera():
    # A floor under the camera, extending far behind it.
    camera = Camera(position=(0.0, 1.0, 0.0), look_at=(0.0, 1.0, 1.0), fov=60.0)
    tris = quad((-20, 0, -20), (20, 0, -20), (20, 0, 20), (-20, 0, 20))
    img = render_image(make_scene(tris, emission=1.0), np.ones((2, 3)), width=W, height=H, camera=camera)
    hit = raycast(camera, W, H, tris) >= 0
    assert hit[-1].all() and not hit[0].any()
    assert ((img[:, :, 0] > 0) == hit).all()


def test_vertex_radiosity_is_area_weighted_within_group_and_crease():
    # Triangles 0, 1: coplanar, sharing the edge (1,0,0)-(0,1,0); areas 0.5 and 1.0.
    # Triangle 2: perpendicular, sharing the corner (0,0,0) with triangle 0 (a crease).
    # Triangle 3: coplanar with 0, sharing the corner (0,0,0) but in another group.
    tris = [((0, 0, 0), (1, 0, 0), (0, 1, 0)),
            ((1, 0, 0), (1, 2, 0), (0, 1, 0)),
            ((0, 0, 0), (0, 1, 0), (0, 0, 1)),
            ((0, 0, 0), (0, -1, 0), (-1, 0, 0))]
    scene = make_scene(tris, emission=1.0, groups=np.array([0, 0, 0, 1]))
    assert scene.areas[1] == pytest.approx(1.0)
    radiosity = np.array([[3.0] * 3, [6.0] * 3, [100.0] * 3, [200.0] * 3])
    c = vertex_radiosity(scene, radiosity)[:, :, 0]
    shared = (0.5 * 3 + 1.0 * 6) / 1.5
    np.testing.assert_allclose(c[0], [3.0, shared, shared])
    np.testing.assert_allclose(c[1], [shared, 6.0, shared])
    np.testing.assert_allclose(c[2], [100.0, 100.0, 100.0])
    np.testing.assert_allclose(c[3], [200.0, 200.0, 200.0])


def test_exposure_and_gamma():
    tris = quad((-1, -1, 2), (1, -1, 2), (1, 1, 2), (-1, 1, 2))
    scene = make_scene(tris, emission=np.zeros((2, 3)))
    img = render_image(scene, np.full((2, 3), 1.0), width=16, height=16, camera=CAMERA, exposure=0.5)
    assert img[8, 8, 0] == round(255 * 0.5 ** (1 / 2.2))
    # Automatic exposure maps this uniform, non-emitting surface to white.
    img = render_image(scene, np.full((2, 3), 0.01), width=16, height=16, camera=CAMERA)
    assert tuple(img[8, 8]) == (255, 255, 255)


def test_default_camera_sees_the_whole_scene():
    cube = []
    for sign in (-1, 1):
        cube += quad((sign, -1, -1), (sign, 1, -1), (sign, 1, 1), (sign, -1, 1))
        cube += quad((-1, sign, -1), (1, sign, -1), (1, sign, 1), (-1, sign, 1))
    scene = make_scene(cube, emission=1.0)
    assert scene.camera is None
    img = render_image(scene, np.ones((scene.patches, 3)), width=32, height=32)
    lit = img[:, :, 0] > 0
    assert lit.sum() > 50
    assert not (lit[0].any() or lit[-1].any() or lit[:, 0].any() or lit[:, -1].any())


def test_cornell_picture(tmp_path):
    """Red wall on the left, green on the right, the light bright at the top centre."""
    s = load_scene("cornell", max_edge=1e9)
    radiosity = s.emission + 0.3 * s.reflectance
    img = render_image(s, radiosity, width=64, height=64)
    left, right = img[32, 3].astype(int), img[32, 60].astype(int)
    assert left[0] > left[1] + 50 and right[1] > right[0] + 50
    assert tuple(img[5, 32]) == (255, 255, 255)               # the light, clipped to white
    path = tmp_path / "c.png"
    save_png(path, img)
    np.testing.assert_array_equal(np.asarray(Image.open(path)), img)


def test_bad_arguments(tmp_path):
    s = load_scene("cornell", max_edge=1e9)
    with pytest.raises(ParameterError, match="width"):
        render_image(s, np.zeros((s.patches, 3)), width=0)
    with pytest.raises(ValueError, match="shape"):
        render_image(s, np.zeros((s.patches + 1, 3)))
    with pytest.raises(ParameterError, match="^--image "):
        save_png(tmp_path / "no" / "such" / "dir.png", np.zeros((4, 4, 3), np.uint8))

"""Contact lines (host_driver/scene/contact.py): patches split where objects rest on them, covered pieces
dropped. Areas are checked against the footprints' closed forms; that the pieces tile the patch is
checked by sampling points with barycentric tests (no shapely, which the splitter uses)."""

import json

import numpy as np
import pytest

from blockray.host_driver.cli import main
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.scene.contact import rounding, split_contacts
from blockray.host_driver.render.render import render

from scenes import balance, closed_box_with_slab, make_scene, prism, rect, rectangle

FLOOR = rectangle((0, 0, 0), (1, 0, 0), (0, 1, 0), 1, 1)          # unit square, z = 0, normal +z


def shoelace(F):
    F = np.asarray(F)
    return 0.5 * abs(np.dot(F[:, 0], np.roll(F[:, 1], -1)) - np.dot(F[:, 1], np.roll(F[:, 0], -1)))


def floor_pieces(scene, normal, origin=(0, 0, 0)):
    """The triangles facing ``normal`` in the plane through ``origin`` (not the boxes' tops)."""
    on = np.abs((scene.centroids - origin) @ normal) < 1e-6 * np.abs(scene.vertices).max()
    return scene.patch_vertices[(scene.normals @ normal > 0.999) & on]


def coverage(pieces, points, normal):
    """(K,) how many of the triangles ``pieces`` contain each point (in their plane); -1 for a point
    within 1e-5 (barycentric) of a piece's edge (not counted: on two pieces, or moved off one by rounding)."""
    count = np.zeros(len(points), dtype=int)
    edge = np.zeros(len(points), dtype=bool)
    for a, b, c in pieces:
        lam = np.stack([np.cross(c - b, points - b) @ normal, np.cross(a - c, points - c) @ normal,
                        np.cross(b - a, points - a) @ normal], axis=1) / (np.cross(b - a, c - a) @ normal)
        count += (lam > 0).all(axis=1)
        edge |= (np.abs(lam) < 1e-5).any(axis=1) & (lam > -1e-5).all(axis=1)
    return np.where(edge, -1, count)


def check_tiling(scene, footprints, transform=lambda p: p, normal=(0, 0, 1)):
    """The floor's pieces cover each sample point once outside the footprints and never inside."""
    g = (np.arange(97) + 0.5) / 97
    uv = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    inside = np.zeros(len(uv), dtype=bool)
    for F in footprints:
        F = np.asarray(F)[:, :2]
        d = np.roll(F, -1, axis=0) - F
        inside |= (((uv[:, None] - F[None]) @ np.array([[0, 1], [-1, 0]]) * d[None]).sum(axis=2) < 0).all(axis=1)
    points = transform(np.column_stack([uv, np.zeros(len(uv))]))
    n = np.asarray(normal, dtype=np.float64)
    got = coverage(floor_pieces(scene, n, transform(np.zeros((1, 3)))[0]), points, n)
    seen = got >= 0
    assert (got[seen & inside] == 0).all() and (got[seen & ~inside] == 1).all()
    assert seen.mean() > 0.9


@pytest.mark.parametrize("bottom", [False, True])
def test_box_on_floor_removes_its_footprint(bottom):
    """A 0.35 x 0.2 box resting on the unit floor: exactly its footprint goes (the floor under an open
    bottom is closed by the four sides; a bottom face is covered too, whole)."""
    foot = rect(0.25, 0.3, 0.6, 0.5)
    scene = make_scene(np.concatenate([FLOOR, prism(foot, 0.4, bottom=bottom)]))
    split, info = split_contacts(scene)
    floor = floor_pieces(split, np.array([0.0, 0.0, 1.0]))
    area = sum(0.5 * np.linalg.norm(np.cross(b - a, c - a)) for a, b, c in floor)
    assert area == pytest.approx(1 - 0.07, abs=1e-14)
    assert info["patches_split"] == 2 and info["patches_covered"] == (2 if bottom else 0)
    assert info["covered_area"] == pytest.approx(0.07 * (2 if bottom else 1), abs=1e-14)
    assert split.patches == len(floor) + 10                  # the box's sides and top as they were
    check_tiling(split, [foot])


def test_split_is_deterministic_and_keeps_corners_exact():
    scene = make_scene(np.concatenate([FLOOR, prism(rect(0.25, 0.3, 0.6, 0.5), 0.4)]))
    a, b = split_contacts(scene)[0], split_contacts(scene)[0]
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.triangles, b.triangles)
    # the floor's and the box's corners are kept as they are; the only new ones are where the outline
    # crosses the floor's diagonal x = y: (0.3, 0.3) and (0.5, 0.5), exactly
    corners = {tuple(v) for v in scene.vertices}
    new = {tuple(v) for v in floor_pieces(a, np.array([0.0, 0.0, 1.0])).reshape(-1, 3)} - corners
    assert new == {(0.3, 0.3, 0.0), (0.5, 0.5, 0.0)}


def rotation(seed):
    q = np.random.default_rng(seed).normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@pytest.mark.parametrize("decimals", [6, 9])
def test_rotated_scaled_rounded_box_still_found(decimals):
    """Rotated, scaled by e and moved, coordinates printed to 6 or 9 decimals: no face is exactly
    coplanar any more, yet the contact is found. The covered area is the footprint's, e^2 0.07, up to
    the rounding: each corner is off by up to sqrt(3)/2 10^-d, moving the outline's area by at most
    its perimeter (1.1 e) times that."""
    R, s, t = rotation(34), np.e, np.array([0.1, -0.3, 0.7])
    foot = rect(0.25, 0.3, 0.6, 0.5)
    tris = np.round(np.concatenate([FLOOR, prism(foot, 0.4)]) * s @ R.T + t, decimals)
    scene = make_scene(tris)
    assert rounding(scene.vertices) == 0.5 * 10.0 ** -decimals
    split, info = split_contacts(scene)
    bound = 1.1 * s * np.sqrt(3) / 2 * 10.0 ** -decimals
    assert info["patches_split"] == 2
    assert abs(info["covered_area"] - 0.07 * s * s) <= bound
    # the box's corners are kept as they are, off the floor's plane by the rounding: the pieces' areas
    # move by as much
    assert abs(split.areas.sum() + info["covered_area"] - scene.areas.sum()) <= bound
    check_tiling(split, [foot], lambda p: p * s @ R.T + t, normal=R @ [0, 0, 1])


def test_random_boxes_on_floor():
    """Seeded: up to four boxes, turned about the vertical, in disjoint quarters of the floor, some with a
    bottom face, the whole scene rotated and printed to 9 decimals."""
    seed = 140
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    parts, feet = [FLOOR], []
    for cx, cy in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)]:
        if rng.random() < 0.2:
            continue
        half, turn = rng.uniform(0.05, 0.15, size=2), rng.uniform(0, np.pi)
        c, s = np.cos(turn), np.sin(turn)
        foot = [(cx + c * u - s * v, cy + s * u + c * v, 0.0) for u, v in
                [(-half[0], -half[1]), (half[0], -half[1]), (half[0], half[1]), (-half[0], half[1])]]
        feet.append(foot)
        parts.append(prism(foot, rng.uniform(0.05, 1), bottom=rng.random() < 0.5))
    R, scale = rotation(seed), rng.uniform(0.3, 30)
    scene = make_scene(np.round(np.concatenate(parts) * scale @ R.T, 9))
    split, info = split_contacts(scene)
    covered = sum(shoelace(np.asarray(f)[:, :2]) for f in feet) * scale ** 2
    # kept corners off the plane by the rounding move the pieces' areas (the test above), on the floor
    # and on the bottom faces
    perimeter = sum(np.linalg.norm(np.roll(f, -1, axis=0) - f, axis=1).sum() for f in feet) * scale
    assert abs(split.areas.sum() + info["covered_area"] - scene.areas.sum()) <= 2 * perimeter * np.sqrt(3) / 2 * 1e-9
    floor_area = sum(0.5 * np.linalg.norm(np.cross(b - a, c - a)) for a, b, c in floor_pieces(split, R @ [0, 0, 1], np.zeros(3)))
    assert floor_area == pytest.approx(scale ** 2 - covered, rel=1e-7)
    check_tiling(split, feet, lambda p: p * scale @ R.T, normal=R @ [0, 0, 1])


@pytest.mark.parametrize("case", ["hovering", "open side", "edge on the floor"])
def test_what_covers_nothing(case):
    """A box 1e-3 above the floor, a box with one side left open (a book on a shelf with a gap
    behind it), a box on one edge (a line contact): the floor is left whole."""
    if case == "hovering":
        box = prism(rect(0.25, 0.3, 0.6, 0.5, z=1e-3), 0.4)
    elif case == "open side":
        box = prism(rect(0.25, 0.3, 0.6, 0.5), 0.4, open_side=2)
    else:
        box = np.array([[(0.3, 0.4, 0.0), (0.6, 0.4, 0.0), (0.45, 0.2, 0.3)],
                        [(0.6, 0.4, 0.0), (0.3, 0.4, 0.0), (0.45, 0.6, 0.3)]])
    scene = make_scene(np.concatenate([FLOOR, box]))
    split, info = split_contacts(scene)
    assert split is scene and info["patches_split"] == info["patches_covered"] == 0


def test_against_a_wall_the_wall_closes_the_footprint():
    """A box pushed against the wall y = 1 with its wall side left out (like the room's bookshelf
    sides): the floor under it is closed by its three sides and the wall; the wall part behind it,
    by its sides, top and the floor."""
    wall = rectangle((0, 1, 0), (1, 0, 0), (0, 0, 1), 1, 1)         # normal -y, into the room
    box = prism(rect(0.2, 0.8, 0.5, 1.0), 0.3, open_side=2)
    scene = make_scene(np.concatenate([FLOOR, wall, box]))
    split, info = split_contacts(scene)
    assert info["covered_area"] == pytest.approx(0.3 * 0.2 + 0.3 * 0.3, abs=1e-14)
    check_tiling(split, [rect(0.2, 0.8, 0.5, 1.0)])


def test_builtin_room_covered_areas():
    """The room's covered areas by hand (host_driver/scene/scenes/make_scenes.py): the back wall loses 3
    sconces (0.4 x 0.12) + 2 bookshelf sides (0.03 x 1.8) + 5 shelves (1.14 x 0.03) = 0.423 m^2; the
    right wall 3 sconces + the sofa back (0.85 x 2.2) and arms (2 x 0.6 x 0.2) = 2.254; the floor 4 table
    legs (0.06^2), 16 chair legs (0.04^2), 2 shelf sides (0.03 x 0.35), the sofa (0.7 x 2.2 + 0.2 x 2.2
    + 2 x 0.9 x 0.2) and the low table's foot (0.54 x 0.94) = 2.9086; the bookshelf the ends of its
    5 shelves on its 2 sides (0.03 x 0.35 each) and the shelf under each of its 4 closed books (0.25
    x 0.25) = 0.355."""
    full = load_scene("room", max_edge=1e9, contact=False)
    cut = load_scene("room", max_edge=1e9)
    lost = {}
    for scene, sign in ((full, 1), (cut, -1)):
        for g, a in zip(scene.group, scene.areas):
            lost[scene.group_names[g]] = lost.get(scene.group_names[g], 0.0) + sign * a
    assert lost["back_wall"] == pytest.approx(0.423, abs=1e-9)
    assert lost["right_wall"] == pytest.approx(2.254, abs=1e-9)
    assert lost["floor"] == pytest.approx(2.9086, abs=1e-9)
    assert lost["bookshelf"] == pytest.approx(0.355, abs=1e-9)
    assert max(abs(lost[g]) for g in ("front_wall", "left_wall", "ceiling")) < 1e-12
    assert cut.contact["patches_split"] > 0 and full.contact is None


def test_energy_balance_better_with_the_split():
    """Golden board: the floor cell under the slab spreads what it receives over its covered part
    unless it is split (measured -2.1%, -1.7%, -2.9%); split, absorbed / emitted - 1 is at least 5
    times smaller in every channel (measured +0.12%, +0.09%, +0.20%: the visibility's own error)."""
    scene = closed_box_with_slab()
    split, info = split_contacts(scene)
    assert info["patches_split"] == 2
    balances = {}
    for name, s in (("whole", scene), ("split", split)):
        result = render(s, backend="golden", tolerance=1e-7)
        balances[name] = balance(s, result.radiosity)
    print(f"{split.patches} patches: absorbed / emitted - 1 = {balances}")
    assert (np.abs(balances["split"]) < 0.2 * np.abs(balances["whole"])).all()


def test_cli_reports_and_turns_off(tmp_path):
    obj = tmp_path / "block.obj"
    tris = np.concatenate([FLOOR, prism(rect(0.25, 0.3, 0.6, 0.5), 0.4)])
    obj.write_text("".join(f"v {float(x)!r} {float(y)!r} {float(z)!r}\n" for x, y, z in tris.reshape(-1, 3))
                   + "".join(f"f {3 * k + 1} {3 * k + 2} {3 * k + 3}\n" for k in range(len(tris))))
    reports = {}
    for mode in ("on", "off"):
        report = tmp_path / f"{mode}.json"
        assert main(["render", str(obj), "--board", "golden", "--max-shots", "1", "--quiet", "--contact", mode,
                     "--report", str(report)]) == 0
        reports[mode] = json.loads(report.read_text())
    assert reports["on"]["contact"]["patches_split"] == 2 and reports["off"]["contact"] is None
    assert reports["on"]["patches"] > reports["off"]["patches"] == 12


@pytest.mark.parametrize("coordinates, delta", [
    ([0.5, 0.25, 1.0], 5e-7),                        # few decimals shown: 6 assumed (exporters print 6)
    ([0.166666667, 0.5, 2.0], 5e-10),                # 9 decimals
    ([1.234567e-12, 2.5e-12, 0.0], 5e-19),           # exponent notation: the 7th significant digit
])
def test_rounding_reads_the_printed_precision(coordinates, delta):
    assert rounding(np.array([coordinates])) == pytest.approx(delta, rel=1e-12)

"""Energy balance of closed scenes: absorbed power sum (1 - rho) H A, with H = (B - E) / rho the
incident flux, equals emitted power sum E A within 0.05% per channel (issue 17).

The scenes are built in tests/scenes.py (``closed_scenes``); benchmarks/bench_formfactor.py prints
the table in docs/formfactors.md from the same scenes.
"""

import numpy as np
import pytest

from blockray.host_driver.radiosity.closure import absorbed_balance
from blockray.host_driver.radiosity.formfactor import form_factor_matrix
from blockray.host_driver.render.render import render
from blockray.host_driver.radiosity.solver import jacobi

from scenes import balance, closed_scenes, make_scene

BALANCE = 5e-4


def _scene(prefix):
    return next(scene for name, scene in closed_scenes() if name.startswith(prefix))


def test_absorbed_balance_formula():
    """A one-patch check of the measure itself: a patch with B = E + rho H absorbs (1 - rho) H A."""
    scene = make_scene(np.zeros((1, 3, 3)) + np.eye(3)[None], reflectance=[0.5, 0.25, 0.8], emission=[1.0, 1.0, 1.0])
    H = np.array([[2.0, 4.0, 1.0]])
    B = scene.emission + scene.reflectance * H
    absorbed = ((1 - scene.reflectance) * H * scene.areas[:, None]).sum(axis=0)
    assert np.allclose(absorbed_balance(scene, B), absorbed / (scene.emission * scene.areas[:, None]).sum(axis=0) - 1)


def test_empty_closed_box_absorbs_what_it_emits():
    """Unoccluded: the exact factors' rows sum to 1, so the balance is to rounding."""
    scene = _scene("empty closed box")
    F = form_factor_matrix(scene)
    result = jacobi(scene, F, tolerance=1e-12, max_iterations=2000)
    balance = absorbed_balance(scene, result.B)
    print(f"empty closed box: absorbed / emitted - 1 = {balance}")
    assert np.abs(balance).max() < 1e-9


@pytest.mark.slow
@pytest.mark.parametrize("prefix", ["empty closed box", "icosphere", "cornell closed"])
def test_closed_scene_render_balance(prefix):
    """Full renders on the golden board (visibility by 8 rays per pair) with view-factor
    enforcement (host_driver/radiosity/closure.py): within 0.05% per channel. The raw factors' balance (not
    within 0.05% with occluders, docs/formfactors.md) is printed from the report."""
    scene = _scene(prefix)
    result = render(scene, backend="golden", tolerance=1e-6, closure="enforce")
    c = result.report["closure"]
    got = balance(scene, result.radiosity)
    print(f"{scene.name} ({scene.patches} patches): absorbed / emitted - 1 = {got}; raw factors "
          f"{c['absorbed_balance_raw']} (summation rule {c['raw_imbalance_from_closure']}, reciprocity "
          f"{c['raw_imbalance_from_reciprocity']}); scale max |d - 1| = {c['scale_max_change']:.2e}")
    assert np.abs(got).max() < BALANCE
    raw_parts = np.add(c["raw_imbalance_from_closure"], c["raw_imbalance_from_reciprocity"])
    # the split adds up, but for the unshot energy of progressive refinement (tolerance 1e-6 of
    # the three channels' emitted power: 7e-6 of the empty box's dim blue channel)
    assert np.allclose(raw_parts, c["absorbed_balance_raw"], atol=2e-5)


def _on_other_surface(points, own, V, normals, tol=1e-6):
    """bool per point: it lies (within ``tol``) on a triangle of V whose plane is not the face
    ``own``'s."""
    other = ~((np.abs(np.abs(normals @ normals[own]) - 1) < 1e-9)
              & (np.abs(((V[:, 0] - V[own, 0]) * normals).sum(axis=1)) < tol))
    a, e1, e2 = V[other, 0], V[other, 1] - V[other, 0], V[other, 2] - V[other, 0]
    d = points[:, None] - a[None]                                          # (P, T, 3)
    height = np.abs((d * normals[other][None]).sum(axis=-1))
    # barycentric coordinates in each triangle's plane (Cramer on the 2 x 2 Gram system)
    g11, g12, g22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    r1, r2 = (d * e1).sum(-1), (d * e2).sum(-1)
    det = g11 * g22 - g12 ** 2
    u, v = (g22 * r1 - g12 * r2) / det, (g11 * r2 - g12 * r1) / det
    return ((height < tol) & (u > -tol) & (v > -tol) & (u + v < 1 + tol)).any(axis=1)


def test_builtin_room_has_no_open_boxes():
    """Every edge of the room's faces (before subdivision) is shared by two of them or rests on
    another surface along its whole length (a contact line, cut at load): no object is open where
    light could get in. Books open at the back once let the wall patches behind them see the
    books' insides (visible row sums of 0.21 there)."""
    from blockray.host_driver.scene.builtin import path
    from blockray.host_driver.scene.objload import load_obj
    raw = load_obj(path("room"), name="room")
    T, V = raw.triangles, raw.vertices[raw.triangles]
    normals = np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    edges = {}
    for t, tri in enumerate(T):
        for k in range(3):
            edges.setdefault(tuple(sorted((tri[k], tri[(k + 1) % 3]))), []).append(t)
    loose = []
    for (a, b), faces in edges.items():
        if len(faces) > 1:
            continue
        p, q = raw.vertices[a], raw.vertices[b]
        if not _on_other_surface(p + np.linspace(0, 1, 9)[:, None] * (q - p), faces[0], V, normals).all():
            loose.append((raw.group_names[raw.group[faces[0]]], p.tolist(), q.tolist()))
    assert not loose, f"{len(loose)} edges bound an open object, e.g. {loose[:3]}"


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_occluded_closed_scene_balances_from_rays_alone(seed):
    """No closure applied: the icosphere in a closed box (512 patches) with ``--estimator balanced``
    (8 stratified drawn end points per pair on the 1/168 lattice, each row from its own drawn set
    of shooter samples, 4x the rows from emitters) balances within 0.05% per channel
    (docs/formfactors.md, "More rows from emitters"); the paper's centroid estimator does not
    (-0.09%, -0.06%, -0.14%), so the test tells the two apart."""
    scene = _scene("icosphere")
    result = render(scene, backend="model", solver="jacobi", tolerance=1e-6, estimator="balanced", end_seed=seed,
                    sample_seed=seed)
    got = balance(scene, result.radiosity)
    print(f"seed {seed}: absorbed / emitted - 1 = {got}")
    assert np.abs(got).max() < BALANCE
    plain = balance(scene, render(scene, backend="model", solver="jacobi", tolerance=1e-6).radiosity)
    print(f"centroid end points, fixed samples: {plain}")
    assert np.abs(plain).max() > BALANCE


@pytest.mark.slow
def test_the_slab_balances_on_every_seed():
    """A slab resting on a closed box's floor, cut along its contact lines (126 patches, two
    emitting): with ``--estimator balanced`` each of 24 seeds is within 0.05% per channel (about
    2 min). Without more rows from its two emitters 2 of the 24 are not (docs/formfactors.md, "More
    rows from emitters"), so the test tells them apart."""
    from blockray.host_driver.scene.contact import split_contacts
    from scenes import closed_box_with_slab
    scene = split_contacts(closed_box_with_slab())[0]
    got = np.array([balance(scene, render(scene, backend="model", solver="jacobi", tolerance=1e-6,
                                          estimator="balanced", end_seed=s, sample_seed=s).radiosity)
                    for s in range(24)])
    print("seeds 0-23: absorbed / emitted - 1 (%)\n", np.round(100 * got, 3))
    assert np.abs(got).max() < BALANCE


@pytest.mark.slow
def test_room_balances_from_rays_alone():
    """The built-in room (3 653 patches, cut along its contact lines) with ``--estimator balanced``
    (8 drawn rows per pair, each from its own set of samples, 32 from its 28 emitting patches):
    within 0.05% per channel from rays alone (about 20 CPU min; the paper's estimator is at +0.8%).
    docs/formfactors.md records seeds 0, 1, 2 and 5; this is seed 0."""
    from blockray.host_driver.scene.builtin import load_scene
    scene = load_scene("room")
    result = render(scene, backend="model", solver="jacobi", tolerance=1e-6, estimator="balanced", end_seed=0,
                    sample_seed=0)
    assert result.report["estimator"] == "balanced" and result.report["rays"] > 5e8
    got = balance(scene, result.radiosity)
    print(f"room: absorbed / emitted - 1 = {got}")
    assert np.abs(got).max() < BALANCE

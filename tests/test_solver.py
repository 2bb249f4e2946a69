"""Radiosity solvers: closed-form cases (prior-art.md D.3) and a direct linear solve."""

import numpy as np
import pytest

from blockray.host_driver.radiosity.formfactor import form_factor_matrix
from blockray.host_driver.radiosity.solver import (ambient, gauss_seidel, jacobi, progressive_refinement,
                                         residual)

from scenes import closed_box, make_scene

RHO = np.array([0.5, 0.3, 0.7])          # per channel, uniform over patches
E0 = np.array([1.0, 2.0, 0.5])


@pytest.fixture(scope="module")
def box():
    tris, face = closed_box(3)
    scene = make_scene(tris, reflectance=RHO, emission=E0)
    return scene, face, form_factor_matrix(scene)


def _solve_all(scene, F, tolerance):
    return {"progressive": progressive_refinement(scene, lambda i: F[:, i], tolerance=tolerance),
            "jacobi": jacobi(scene, F, tolerance=tolerance),
            "gauss-seidel": gauss_seidel(scene, F, tolerance=tolerance)}


def test_closed_box_uniform_emission(box):
    """Uniform E and rho in a closed box: B = E / (1 - rho) on every patch, every channel."""
    scene, _, F = box
    expected = E0 / (1 - RHO)
    for name, result in _solve_all(scene, F, 1e-4).items():
        err = np.abs(result.B / expected - 1).max()
        print(f"{name}: shots={result.shots} iterations={result.iterations} "
              f"residual={result.residual:.2e} max relative error of B={err:.2e}")
        assert result.converged and result.residual < 1e-4
        assert err < 0.01
        A = scene.areas
        balance = (A[:, None] * result.B).sum(axis=0) / ((A[:, None] * scene.emission).sum(axis=0) / (1 - RHO))
        assert np.abs(balance - 1).max() < 0.01


@pytest.mark.parametrize("emitter", ["corner patch", "one face"])
def test_closed_box_energy_balance(emitter):
    """Non-uniform emission, uniform rho: sum A B = sum A E / (1 - rho) per channel (D.3)."""
    tris, face = closed_box(4)
    E = np.zeros((len(tris), 3))
    if emitter == "corner patch":
        E[0] = E0                     # a triangle touching an edge of the box: the hardest case
    else:
        E[face == 1] = E0
    scene = make_scene(tris, reflectance=RHO, emission=E)
    F = form_factor_matrix(scene)
    A = scene.areas
    target = (A[:, None] * E).sum(axis=0) / (1 - RHO)
    results = _solve_all(scene, F, 1e-6)
    for name, result in results.items():
        balance = (A[:, None] * result.B).sum(axis=0) / target - 1
        print(f"{emitter}, {name}: energy balance error per channel {balance}")
        assert np.abs(balance).max() < 0.01
    assert np.allclose(results["progressive"].B, results["gauss-seidel"].B, rtol=1e-4, atol=1e-6)


def test_solvers_match_direct_solve():
    """An arbitrary non-symmetric F (rows sum < 1): every solver against numpy's linear solve."""
    seed = 31337
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    N = 40
    scene = make_scene(rng.uniform(0, 1, (N, 3, 3)), reflectance=rng.uniform(0, 0.9, (N, 3)),
                       emission=rng.uniform(0, 1, (N, 3)) * (rng.uniform(size=(N, 1)) < 0.2))
    F = rng.uniform(0, 1, (N, N)) ** 4
    np.fill_diagonal(F, 0)
    F /= F.sum(axis=1, keepdims=True) * rng.uniform(1.0, 1.5, (N, 1))
    exact = np.stack([np.linalg.solve(np.eye(N) - scene.reflectance[:, c, None] * F, scene.emission[:, c])
                      for c in range(3)], axis=1)
    for name, result in _solve_all(scene, F, 1e-8).items():
        assert result.converged, name
        assert np.allclose(result.B, exact, rtol=1e-6, atol=1e-9), name
        assert residual(scene, F, exact) < 1e-12
        if name != "progressive":
            assert result.residual == pytest.approx(residual(scene, F, result.B), rel=1e-12)


def test_progressive_history_and_limits(box):
    scene, _, F = box
    calls = []

    def shoot(i):
        calls.append(i)
        return F[:, i]

    result = progressive_refinement(scene, shoot, tolerance=1e-6, max_shots=25)
    assert result.shots == 25 == len(calls) and not result.converged
    h = np.array(result.history)
    assert len(h) == 26 and h[0] == pytest.approx(1.0, rel=1e-12)
    assert (np.diff(h) < 0).all()                       # unshot energy falls with every shot
    A = scene.areas
    assert result.residual == pytest.approx((A[:, None] * result.U).sum() / (A[:, None] * scene.emission).sum())
    # the first shooter is the largest A_i * sum(U_i): all equal here, so patch 0 (argmax tie rule)
    assert calls[0] == int(np.argmax(A * scene.emission.sum(axis=1)))
    amb = ambient(scene, result.U)
    assert amb.shape == (3,) and (amb > 0).all()


def test_progressive_batched(box):
    scene, _, F = box
    rounds = []

    def shoot_many(ids):
        rounds.append(list(ids))
        return F[:, ids].T

    single = progressive_refinement(scene, lambda i: F[:, i], tolerance=1e-5)
    batched = progressive_refinement(scene, None, tolerance=1e-5, shoot_many=shoot_many, batch=8)
    assert batched.converged
    assert all(len(r) == 8 for r in rounds[:-1]) and len(set(rounds[0])) == 8
    assert np.allclose(batched.B, single.B, rtol=1e-4)
    for cap in (20, 17):                                # last rounds of 4 and of 1
        capped = progressive_refinement(scene, None, tolerance=1e-9, shoot_many=shoot_many, batch=8,
                                        max_shots=cap)
        assert capped.shots == cap and len(rounds[-1]) == cap % 8


def test_no_emission_and_bad_shapes(box):
    scene, _, F = box
    dark = make_scene(scene.patch_vertices, reflectance=RHO, emission=0.0)
    for result in _solve_all(dark, F, 1e-3).values():
        assert result.converged and (result.B == 0).all()
    with pytest.raises(ValueError):
        progressive_refinement(scene, lambda i: F[:5, i])
    with pytest.raises(ValueError):
        jacobi(scene, F[:5])


def test_progress_reports(box):
    scene, _, F = box
    seen = []
    progressive_refinement(scene, lambda i: F[:, i], max_shots=5, progress=lambda k, r: seen.append((k, r)))
    assert [k for k, _ in seen] == [1, 2, 3, 4, 5]

    class Bar:
        n = 0

        def update(self, k):
            self.n += k

    bar = Bar()
    result = gauss_seidel(scene, F, tolerance=1e-6, progress=bar)
    assert bar.n == result.iterations > 0


def test_gauss_seidel_needs_fewer_sweeps(box):
    scene, _, F = box
    j, g = jacobi(scene, F, tolerance=1e-6), gauss_seidel(scene, F, tolerance=1e-6)
    print(f"sweeps to 1e-6: jacobi {j.iterations}, gauss-seidel {g.iterations}")
    assert g.iterations < j.iterations


def test_first_shot_from_a_square_light():
    """D.3 diagnostic: after the light's shots, B_j = rho_j E_L F_{j -> L}, with F from the
    closed form for a differential element under a rectangle (four corner rectangles)."""
    from blockray.host_driver.radiosity.formfactor import unoccluded_factors
    from oracles import corner_closed_form
    from scenes import rectangle

    c = 0.8
    light = rectangle([0, 0, c], [0, 1, 0], [1, 0, 0], 1, 1)            # unit square, normal -z
    feet = np.array([[0.5, 0.5], [0.1, 0.2], [0.9, 0.05], [0.3, 0.7]])
    small = rectangle([0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], 1, 1)[:1]  # a tiny floor triangle
    receivers = np.stack([small[0] - small[0].mean(axis=0) + [x, y, 0] for x, y in feet])
    E_L = np.array([3.0, 2.0, 1.0])
    rho = np.array([0.6, 0.5, 0.4])
    emission = np.concatenate([np.tile(E_L, (2, 1)), np.zeros((len(feet), 3))])
    scene = make_scene(np.concatenate([light, receivers]), reflectance=rho, emission=emission)
    # the exact patch factor of a tiny receiver is within 1e-4 of the point factor at its centroid
    default = progressive_refinement(scene, lambda i: unoccluded_factors(scene, i), max_shots=2)
    assert default.shots == 2
    for j in range(len(feet)):
        foot = scene.centroids[2 + j, :2]
        F = sum(corner_closed_form(a, b, c) for a in (foot[0], 1 - foot[0]) for b in (foot[1], 1 - foot[1]))
        assert default.B[2 + j] == pytest.approx(rho * E_L * F, rel=1e-4)


def test_compiled_shot_is_the_numpy_arithmetic():
    """One shot in the compiled kernel, bit for bit the numpy expressions it replaces (random
    scenes of many magnitudes, zero reflectances, factors and unshot rows; seeded)."""
    from blockray.host_driver.radiosity.solver import _shoot
    seed = 1305
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    for _ in range(100):
        N = int(rng.integers(1, 300))
        A = rng.random(N) * 10 ** rng.uniform(-3, 3, N)
        rho = rng.random((N, 3)) * (rng.random((N, 3)) > 0.2)
        U = rng.random((N, 3)) * 10 ** rng.uniform(-8, 2, (N, 1)) * (rng.random((N, 1)) > 0.1)
        B = U + rng.random((N, 3))
        F = rng.random(N) * (rng.random(N) < 0.7)
        i = int(rng.integers(N))
        dB = rho * (F[:, None] * U[i][None, :])
        dB[i] = 0.0
        B_np, U_np = B + dB, U + dB
        U_np[i] = 0.0
        energy = np.empty(N)
        _shoot(B, U, rho, F, i, A, energy)
        assert np.array_equal(B, B_np) and np.array_equal(U, U_np)
        assert np.array_equal(energy.view(np.int64), (A * U_np.sum(axis=1)).view(np.int64))

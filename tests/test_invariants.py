"""Run-time invariants of the solvers and the render (issue 34): no non-finite radiosity, form
factor or residual is written, and a solve that would diverge ends with one line, exit status 2,
naming the patch (host_driver/radiosity/solver.py, "Invariants")."""

import json

import numpy as np
import pytest

from blockray.errors import SolveError
from blockray.host_driver.radiosity import formfactor, solver
from blockray.host_driver.radiosity.closure import absorbed_balance
from blockray.host_driver.radiosity.formfactor import form_factor_matrix
from blockray.host_driver.scene.objload import load_obj
from blockray.host_driver.render.output import write_patches_csv, write_report_json
from blockray.host_driver.render.render import render

from scenes import closed_box, make_scene
from clirun import assert_one_line_error, cli
from scenes import BOX, BOX_MTL, write

SOLVERS = ["progressive", "jacobi", "gauss-seidel"]


@pytest.fixture(scope="module")
def box():
    """A closed box, every patch emitting: its exact factors' rows sum to 1, so every gain is rho."""
    tris, _ = closed_box(2)
    scene = make_scene(tris, reflectance=[0.5, 0.3, 0.7], emission=[1.0, 2.0, 0.5])
    return scene, form_factor_matrix(scene)


def _outputs(tmp_path):
    return {option: tmp_path / name for option, name in
            (("--image", "out.png"), ("--patches", "out.csv"), ("--report", "out.json"))}


def _render_cli(capsys, tmp_path, solver_name, *extra):
    path = write(tmp_path, BOX, BOX_MTL, name="box")
    outputs = _outputs(tmp_path)
    argv = ["render", path, "--board", "golden", "--solver", solver_name, "--quiet", "--size", "16", *extra]
    for option, out in outputs.items():
        argv += [option, out]
    code, err = cli(capsys, argv)
    return code, err, outputs


@pytest.mark.parametrize("solver_name", SOLVERS)
def test_correct_render_passes_and_reports_row_sums_and_balance(tmp_path, capsys, solver_name):
    code, err, outputs = _render_cli(capsys, tmp_path, solver_name)
    assert code == 0, err
    report = json.loads(outputs["--report"].read_text())
    rows = report["visible_row_sum"]
    print(f"{solver_name}: visible_row_sum {rows}, absorbed_balance {report['absorbed_balance']}")
    assert 0 < rows["max"] <= 1 and 0 < rows["gain_max"] <= rows["max"]
    assert 0 <= rows["patch"] < report["patches"] and 0 <= rows["gain_patch"] < report["patches"]
    # the open box loses light through its open sides: the balance is negative, the same
    # number as closure.absorbed_balance of the written radiosity
    scene = load_obj(tmp_path / "box.obj")
    B = np.loadtxt(outputs["--patches"], delimiter=",", skiprows=1, usecols=(6, 7, 8))
    np.testing.assert_allclose(report["absorbed_balance"], absorbed_balance(scene, B), rtol=1e-12, atol=1e-15)
    assert all(-1 < b < 0 for b in report["absorbed_balance"])


def test_the_summary_line_gives_the_energy_balance_and_the_estimator(tmp_path, capsys):
    path = write(tmp_path, BOX, BOX_MTL, name="box")
    report = tmp_path / "r.json"
    code, err = cli(capsys, ["render", path, "--board", "golden", "--estimator", "balanced", "--report", report])
    assert code == 0, err
    balance = json.loads(report.read_text())["absorbed_balance"]
    line = next(x for x in err.splitlines() if x.startswith("energy: "))
    assert line == ("energy: absorbed / emitted - 1 = " + ", ".join(f"{b:+.1e}" for b in balance)
                    + " (0 in a closed scene; estimator balanced, docs/formfactors.md)"), line


def test_closed_box_balance_is_zero_and_a_dark_channel_is_null(box):
    scene, _ = box
    scene.emission[:, 2] = 0.0                  # nothing emits blue
    result = render(scene, backend="golden", solver="jacobi", tolerance=1e-10)
    r, g, b = result.report["absorbed_balance"]
    print(f"closed box: absorbed / emitted - 1 = {r}, {g}; blue {b}")
    assert abs(r) < 1e-3 and abs(g) < 1e-3 and b is None
    assert result.report["visible_row_sum"]["max"] == pytest.approx(1, abs=1e-3)


def _corrupt(monkeypatch, how):
    real = formfactor.unoccluded_factors

    def corrupted(scene, i, **kwargs):
        return how(real(scene, i, **kwargs))
    monkeypatch.setattr(formfactor, "unoccluded_factors", corrupted)


def _nothing_written(outputs):
    assert not any(out.exists() for out in outputs.values()), [str(o) for o in outputs.values() if o.exists()]


@pytest.mark.parametrize("solver_name", SOLVERS)
def test_factors_three_times_too_large_are_refused_naming_the_shooter(tmp_path, capsys, monkeypatch, solver_name):
    _corrupt(monkeypatch, lambda f: 3 * f)
    code, err, outputs = _render_cli(capsys, tmp_path, solver_name)
    assert_one_line_error(code, err, "form factors wrong: shooter patch ", "times the light it sends",
                          "the solve would diverge")
    _nothing_written(outputs)


@pytest.mark.parametrize("solver_name", SOLVERS)
@pytest.mark.parametrize("bad", [np.nan, np.inf, -0.25])
def test_a_factor_that_is_not_finite_or_negative_is_refused(tmp_path, capsys, monkeypatch, solver_name, bad):
    def spoil(f):
        f = f.copy()
        f[np.flatnonzero(f > 0)[-1]] = bad
        return f
    _corrupt(monkeypatch, spoil)
    code, err, outputs = _render_cli(capsys, tmp_path, solver_name)
    assert_one_line_error(code, err, "form factors wrong: the ", " factor from patch ", f"is {bad!r}",
                          "not a finite number >= 0")
    _nothing_written(outputs)


def test_progressive_divergence_names_the_largest_row_sum(box):
    # the solver alone (no gain check): the unshot energy of 3x factors grows past twice its start
    scene, F = box
    shots = []
    with pytest.raises(SolveError) as info:
        solver.progressive_refinement(scene, lambda i: 3 * F[:, i], tolerance=1e-6,
                                      progress=lambda k, r: shots.append(r))
    message = str(info.value)
    print(message)
    assert message.startswith("solve diverged: the unshot energy grew from 1 to ")
    assert "the largest visible row sum is patch " in message and "(form factors wrong?)" in message
    assert shots and max(shots) <= solver.DIVERGED        # stopped at the first shot past the bound


@pytest.mark.parametrize("gather", [solver.jacobi, solver.gauss_seidel])
def test_gathering_divergence_names_the_largest_row_sum(box, gather):
    scene, F = box
    with pytest.raises(SolveError) as info:
        gather(scene, 3 * F, tolerance=1e-6)
    message = str(info.value)
    print(message)
    assert message.startswith("solve diverged: the residual grew from ")
    sums = solver.column_sums(scene, 3 * F)
    assert f"the largest visible row sum is patch {sums.patch}'s, {sums.largest:.6g}" in message
    assert sums.largest == pytest.approx(3, rel=1e-6)


def test_sweeps_without_the_matrix_name_the_patch_that_moved_or_went_non_finite(box):
    # the host + board sets' form (host_driver/cluster/cluster.py): only the sweep is known
    scene, F = box
    E, rho = scene.emission, scene.reflectance
    with pytest.raises(SolveError, match=r"residual grew from .* after \d+ sweeps; patch \d+'s radiosity moved most"):
        solver.jacobi_sweeps(scene, lambda B: E + rho * solver.product(3 * F, B), tolerance=1e-6)

    def poisoned(B):
        new = E + rho * solver.product(F, B)
        new[5, 1] = np.nan
        return new
    with pytest.raises(SolveError, match=r"residual grew from .* to nan after 0 sweeps; patch 5's radiosity became"):
        solver.jacobi_sweeps(scene, poisoned, tolerance=1e-12)
    # Gauss-Seidel's residual is of the sweep's start: the NaN shows one sweep later, still at patch 5
    weighted = lambda B: float((scene.areas[:, None] * np.abs(B - E - rho * solver.product(F, B))).sum())
    with pytest.raises(SolveError, match=r"residual grew from .* to nan after 1 sweeps; patch 5's radiosity became"):
        solver.gauss_seidel_sweeps(scene, lambda B: (weighted(B), poisoned(B)), tolerance=1e-12)


def test_correct_solves_stay_below_the_bound(box):
    """With exact factors every measure only falls: its largest value is its start."""
    scene, F = box
    for result in (solver.progressive_refinement(scene, lambda i: F[:, i], tolerance=1e-9, refuse_gain=True),
                   solver.jacobi(scene, F, tolerance=1e-12), solver.gauss_seidel(scene, F, tolerance=1e-12)):
        history = np.array(result.history)
        assert result.converged and history.max() <= history[0] * (1 + 1e-12), result.solver
    assert result.row_sums is None or result.row_sums.gain <= 1


def test_gain_allowance_covers_the_kernels_error_bound():
    # a kernel held to a looser relative bound would need a larger allowance (solver.GAIN_ALLOWANCE)
    assert solver.GAIN_ALLOWANCE >= formfactor.FAR_TARGET


def test_writers_refuse_non_finite_numbers_and_leave_no_file(tmp_path, box):
    scene, _ = box
    B = np.ones((scene.patches, 3))
    B[7, 2] = np.inf
    with pytest.raises(SolveError, match=r"^patches .*: patch 7's radiosity is \[1.0, 1.0, inf\]; not written"):
        write_patches_csv(tmp_path / "p.csv", scene, B)
    with pytest.raises(SolveError, match=r"^report .*: report\['seconds'\]\['solve'\] is not a finite number"):
        write_report_json(tmp_path / "r.json", {"residual": 0.5, "seconds": {"solve": np.float64("nan")}})
    assert not any(tmp_path.iterdir())


def test_check_finite_names_the_patch(box):
    scene, _ = box
    result = solver.SolveResult(B=np.ones((scene.patches, 3)), U=np.zeros((scene.patches, 3)), solver="jacobi",
                                iterations=4, residual=0.1)
    result.B[3, 0] = np.nan
    with pytest.raises(SolveError, match=r"patch 3's radiosity is \[nan, 1.0, 1.0\] after 4 sweeps"):
        solver.check_finite(scene, result)
    result.B[3, 0], result.residual = 1.0, float("inf")
    with pytest.raises(SolveError, match="the residual is inf after 4 sweeps"):
        solver.check_finite(scene, result)


def test_row_sums_of_the_sets_totals_are_those_of_the_columns(box):
    # host + board sets send each shooter's share of the sums (host_driver/cluster/cluster.py)
    scene, F = box
    A = scene.areas
    whole = solver.column_sums(scene, F)
    halves = [slice(0, 20), slice(20, None)]
    power = sum(A[h] @ F[h] for h in halves)
    gain = sum(F[h].T @ (scene.reflectance[h] * A[h, None]) for h in halves)
    sets = solver.RowSums.of_totals(scene, power, gain)
    assert (sets.patch, sets.gain_patch) == (whole.patch, whole.gain_patch)
    assert sets.largest == pytest.approx(whole.largest, rel=1e-12) and sets.gain == pytest.approx(whole.gain, rel=1e-12)
    with pytest.raises(SolveError, match=r"shooter patch \d+ would get back 2.1 times the light it sends"):
        solver.RowSums.of_totals(scene, 3 * power, 3 * gain, refuse_gain=True)

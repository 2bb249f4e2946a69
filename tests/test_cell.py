"""The processor cell as one object (blockray/cell.py): its kinds, the formats each kind takes,
the default format at B, and the one-line errors naming the parameter the CLI maps to its option."""

import pytest

from blockray.cell import CELLS, Cell, check_cell
from blockray.errors import ParameterError
from blockray.filtered import FilterFormat
from blockray.host_driver.cli import main


def test_the_default_formats():
    # filtered: d_k exact (B + 1 bits, at most 18), w_k at 18 bits; lean: 9 x 9 bits, d_k exact below B = 8
    assert Cell("filtered").format_at(16) == FilterFormat(17, 18)
    assert Cell("filtered").format_at(17) == Cell("filtered").format_at(20) == FilterFormat(18, 18)
    assert Cell("lean").format_at(16) == FilterFormat(9, 9) and Cell("lean").format_at(6) == FilterFormat(7, 9)
    assert Cell().format_at(16) is None and Cell("exact") == Cell()
    asked = FilterFormat(3, 4, 5)
    assert Cell("lean", asked).format_at(16) == asked
    assert Cell("filtered").at(8) == Cell("filtered", FilterFormat(9, 18))
    assert [Cell(k).filtered for k in CELLS] == [False, True, True]
    assert [Cell(k).lean for k in CELLS] == [False, False, True]


@pytest.mark.parametrize("kind,fmt,parameter,message", [
    ("fast", None, "cell", "cell must be one of exact, filtered, lean, not 'fast'"),
    (None, None, "cell", "cell must be one of"),
    ("exact", FilterFormat(9, 9), "filter_bits", "it needs cell filtered or lean, not 'exact'"),
    ("filtered", FilterFormat(9, 9, 12), "filter_bits", "only the lean cell"),
    ("lean", (9, 9), "filter_bits", "filter_bits must be a FilterFormat"),
])
def test_a_bad_cell_names_its_parameter(kind, fmt, parameter, message):
    with pytest.raises(ParameterError, match=message) as e:
        Cell(kind, fmt)
    assert e.value.parameter == parameter
    assert "\n" not in str(e.value)


def test_only_the_lean_cell_takes_rounded_inputs():
    assert Cell("lean", FilterFormat(9, 9, 12)).format == FilterFormat(9, 9, 12)


def test_a_kind_name_is_not_a_cell():
    assert check_cell(Cell("lean")) == Cell("lean")
    with pytest.raises(ParameterError, match="cell must be a Cell") as e:
        check_cell("filtered")
    assert e.value.parameter == "cell"


@pytest.mark.parametrize("argv,expect", [
    (["--cell", "fast"], "--cell must be one of exact, filtered, lean, not 'fast'"),
    (["--filter-bits", "9"], "--filter-bits sets the filter's format; it needs cell filtered or lean, not 'exact'"),
    (["--cell", "filtered", "--filter-bits", "9:x"], "--filter-bits must be D, D:W or D:W:I (integers), not '9:x'"),
    (["--cell", "lean", "--filter-bits", "9:9:9:9"], "--filter-bits must be D, D:W or D:W:I (integers), not '9:9:9:9'"),
    (["--cell", "filtered", "--filter-bits", "9:9:12"], "--filter-bits: filter d9w9i12 rounds w_k from its inputs, which only the lean cell does"),
])
def test_the_cli_names_the_option(tmp_path, capsys, argv, expect):
    assert main(["verilog", "cell", "--out", str(tmp_path / "cell.v")] + argv) == 2
    err = capsys.readouterr().err
    assert err == f"blockray: error: {expect}\n"


def test_filter_bits_takes_the_lean_cells_input_width():
    from blockray.host_driver.render.options import cell_option
    assert cell_option("lean", "9:12:10") == Cell("lean", FilterFormat(9, 12, 10))
    assert cell_option("lean", "9:12") == Cell("lean", FilterFormat(9, 12))
    assert cell_option("filtered", "11") == Cell("filtered", FilterFormat(11, 11))


def test_a_lean_cell_with_rounded_inputs_renders_the_exact_cells_radiosity(tmp_path, capsys):
    """The filter is certified, so however w_k is formed the answers, and so the CSV, are the exact
    cell's; only the undecided tests, sent to the exact unit, cost cycles."""
    from scenes import room_obj
    scene = str(room_obj(tmp_path))
    csv = {}
    for name, cell in [("exact", ["--cell", "exact"]), ("rounded", ["--cell", "lean", "--filter-bits", "8:8:10"])]:
        out = tmp_path / f"{name}.csv"
        assert main(["render", scene, "--max-edge", "1.0", "--voxels", "3", "--board", "model", "--quiet",
                     "--patches", str(out)] + cell) == 0, capsys.readouterr().err
        csv[name] = out.read_bytes()
    assert csv["rounded"] == csv["exact"]

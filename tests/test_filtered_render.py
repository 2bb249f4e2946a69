"""Radiosity with the filtered cell (``--cell filtered``) equals the exact cell's bit for bit.

The filtered array's blocked bits are the exact predicate's by construction (undecided tests go
to its exact unit); only the cycles differ. The small room scene (the rtl_room fixture, tests/conftest.py)
(2 x 2 array, P = 2, B = 10) through the model board, the model behind the byte link, and the
board's RTL under Verilator; cornell through ``--board model`` and ``--board verilator`` is
``-m slow``.
"""

import json

import numpy as np
import pytest

from blockray.cell import Cell
from blockray.filtered import FilterFormat
from blockray.host_driver.cli import main
from blockray.host_driver.render.render import render

from scenes import RTL_BITS as BITS, RTL_PARAMS as PARAMS


@pytest.fixture(scope="module")
def scene(rtl_room):
    return rtl_room


def _render(scene, board, **cell):
    return render(scene, backend=board, params=PARAMS, bits=BITS, samples=4, max_shots=2, voxels=3, **cell)


@pytest.fixture(scope="module")
def exact(scene):
    return _render(scene, "model")


@pytest.mark.parametrize("fmt", [None, FilterFormat(3, 3)])
def test_model_filtered_equals_exact(scene, exact, fmt):
    got = _render(scene, "model", cell=Cell("filtered", fmt))
    assert np.array_equal(got.radiosity, exact.radiosity)
    for key in ("tests_issued", "tests_useful", "blocks", "rays"):
        assert got.report[key] == exact.report[key], key
    print(f"{fmt}: board_cycles exact {exact.report['board_cycles']}, filtered {got.report['board_cycles']}")
    # the filtered array's least latency is longer (the drain of each batch); a narrow filter
    # sends many tests to the shared exact unit and the broadcast stalls
    assert got.report["board_cycles"] > exact.report["board_cycles"]
    if fmt is not None:
        assert (np.array(got.report["board_cycles_per_board"]) > np.array(exact.report["board_cycles_per_board"])).all()


def test_model_link_filtered_counts_the_model_boards_cycles(scene):
    """The host driver over the byte link, answered by BoardModel with the filtered cell: the same
    bits and per-board cycles as ModelBoard with it (both: a full command stream)."""
    cell = Cell("filtered", FilterFormat(3, 3))
    model = _render(scene, "model", cell=cell)
    link = _render(scene, "model-link", cell=cell)
    assert np.array_equal(link.radiosity, model.radiosity)
    for key in ("board_cycles_per_board", "tests_issued_per_board", "load_cycles_per_board"):
        assert link.report[key] == model.report[key], key


def test_cell_errors_name_the_option(capsys):
    assert main(["render", "cornell", "--board", "golden", "--cell", "filtered"]) == 2
    assert "--cell" in capsys.readouterr().err
    assert main(["render", "cornell", "--cell", "fast"]) == 2
    assert "cell" in capsys.readouterr().err
    assert main(["render", "cornell", "--filter-bits", "9"]) == 2
    assert "needs cell filtered or lean" in capsys.readouterr().err


@pytest.mark.cocotb
@pytest.mark.parametrize("kind", ["filtered", "lean"])
def test_verilator_filtered_equals_exact(scene, exact, kind):
    """The filtered or lean board's Verilog under Verilator (host driver, byte link): the exact
    cell's radiosity bit for bit and the model's board cycles, the filter narrow enough (3 x 3
    bits) that the shared exact unit and the credits are exercised."""
    cell = Cell(kind, FilterFormat(3, 3))
    got, model = _render(scene, "verilator", cell=cell), _render(scene, "model", cell=cell)
    assert np.array_equal(got.radiosity, exact.radiosity)
    assert got.report["tests_issued"] == exact.report["tests_issued"]
    assert got.report["board_cycles_per_board"] == model.report["board_cycles_per_board"]
    print(f"board_cycles per board: verilator {kind} {got.report['board_cycles_per_board']}, "
          f"exact {exact.report['board_cycles_per_board']}")


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["filtered", "lean"])
def test_cornell_filtered_equals_exact(tmp_path, kind):
    """``blockray render cornell --cell KIND`` on ``--board model`` and ``verilator``: the
    per-patch radiosity of the exact cell's model byte for byte, and the RTL's board cycles the
    model's."""
    out = {}
    for cell, name in (("exact", "model"), (kind, "model"), (kind, "verilator")):
        csv, report = tmp_path / f"{cell}-{name}.csv", tmp_path / f"{cell}-{name}.json"
        assert main(["render", "cornell", "--board", name, "--cell", cell, "--quiet", "--patches", str(csv),
                     "--report", str(report)]) == 0
        out[cell, name] = (csv.read_bytes(), json.loads(report.read_text()))
    exact, model, rtl = out["exact", "model"], out[kind, "model"], out[kind, "verilator"]
    assert model[0] == exact[0] and rtl[0] == exact[0]
    assert rtl[1]["board_cycles_per_board"] == model[1]["board_cycles_per_board"]
    print(f"board_cycles: exact {exact[1]['board_cycles']}, {kind} {model[1]['board_cycles']}")

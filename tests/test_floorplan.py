"""The DSP floorplan (synth/floorplan.py, ``blockray synth --dsp-floorplan``): site names as nextpnr
names them, balanced plans on random unit sets, plan files and their errors, and nextpnr placing
the multipliers where the plan locked them."""

import json
import math
import random

import pytest

from blockray.errors import ParameterError
from blockray.host_driver.cli import main
from blockray.synth.floorplan import DSP_COLUMNS, DSP_ROWS, balanced_plan, dsp_units, lock_dsps, read_plan, site

from clirun import assert_one_line_error, cli

# BELs nextpnr-ecp5 chose for multipliers of the lean 2 x 8 and 2 x 7 (placed.json, NEXTPNR_BEL)
NEXTPNR_PLACED = ["X40/Y10/MULT18_0", "X31/Y10/MULT18_0", "X17/Y10/MULT18_4", "X50/Y34/MULT18_1",
                  "X36/Y58/MULT18_5", "X119/Y34/MULT18_5", "X118/Y34/MULT18_4", "X69/Y58/MULT18_0",
                  "X4/Y10/MULT18_0", "X115/Y34/MULT18_1", "X74/Y10/MULT18_5", "X82/Y34/MULT18_4"]
LEAN_2X8 = {"receiver_0": 24, "receiver_1": 24, "resolve": 12, **{f"shooter_{s}": 6 for s in range(8)}}


def test_site_names_are_nextpnrs():
    names = {site(i, y) for i in range(len(DSP_COLUMNS)) for y in DSP_ROWS}
    assert len(names) == 156 == 3 * 52                 # the LFE5U-85F's MULT18X18D
    assert set(NEXTPNR_PLACED) <= names


def _check(plan, sizes):
    """Every unit once, whole, on free sites of a DSP row; returns the multipliers per row."""
    seen, taken, per_row = [], set(), {}
    for y, row in plan.items():
        assert y in DSP_ROWS
        for unit, start in row:
            seen.append(unit)
            sites = {(y, start + i) for i in range(sizes[unit])}
            assert all(0 <= i < 52 for _, i in sites) and not sites & taken, (unit, start)
            taken |= sites
            per_row[y] = per_row.get(y, 0) + sizes[unit]
    assert sorted(seen) == sorted(sizes)
    return per_row


def test_balanced_plan_of_the_lean_2x8_fills_the_rows_evenly():
    plan = balanced_plan(LEAN_2X8)
    assert _check(plan, LEAN_2X8) == {10: 36, 34: 36, 58: 36}
    assert [u for u, _ in plan[34]] == [f"shooter_{s}" for s in range(6)]      # the columns in order


def test_balanced_plans_of_random_units():
    seed = random.randrange(1 << 30)
    print("seed", seed)
    rng = random.Random(seed)
    for _ in range(300):
        sizes = {f"receiver_{r}": rng.choice([6, 24]) for r in range(rng.randint(0, 4))}
        sizes.update({f"shooter_{s}": rng.choice([2, 6]) for s in range(rng.randint(1, 12))})
        if rng.random() < 0.7:
            sizes["resolve"] = rng.choice([12, 18, 48])
        total = sum(sizes.values())
        if total > 156:
            with pytest.raises(ParameterError):
                balanced_plan(sizes)
            continue
        try:
            per_row = _check(balanced_plan(sizes), sizes)
        except ParameterError:          # whole units may not pack: only when the rows are nearly full
            assert total > 156 - 3 * max(sizes.values())
            continue
        # no row above the even share by more than the largest unit
        assert max(per_row.values()) <= math.ceil(total / 3) + max(sizes.values()), (sizes, per_row)


def _netlist(tmp_path, sizes, extra=()):
    cells = {f"dut.{u}.p{i}_dsp": {"type": "MULT18X18D", "attributes": {}} for u, n in sizes.items()
             for i in range(n)}
    cells.update({name: {"type": "LUT4", "attributes": {}} for name in extra})
    path = tmp_path / "top.json"
    path.write_text(json.dumps({"modules": {"x": {"attributes": {}, "cells": {}},
                                            "top": {"attributes": {"top": "1"}, "cells": cells}}}))
    return path


def test_lock_dsps_writes_a_bel_for_every_multiplier(tmp_path):
    path = _netlist(tmp_path, LEAN_2X8, extra=["dut.cell_0_0.lut"])
    used = lock_dsps(path, "balanced")
    assert used["per_row"] == {"10": 36, "34": 36, "58": 36}
    cells = json.loads(path.read_text())["modules"]["top"]["cells"]
    bels = [c["attributes"]["BEL"] for c in cells.values() if c["type"] == "MULT18X18D"]
    assert len(bels) == len(set(bels)) == 108
    assert "BEL" not in cells["dut.cell_0_0.lut"]["attributes"]
    # a unit's multipliers on consecutive sites, in the order of their names (p2 after p1, p10 last)
    row = [cells[f"dut.shooter_0.p{i}_dsp"]["attributes"]["BEL"] for i in range(6)]
    assert row == [site(2 + i, 34) for i in range(6)]


def test_units_of_harness_and_board_netlists():
    cells = {n: {"type": "MULT18X18D"} for n in [
        "dut.receiver_0.pq_0_p17_dsp", "dut.resolve.exact.w_1_dsp", "dut.p_0_dsp",
        "core.board.array.shooter_2.pp_1_dsp", "core.board.array.resolve.exact.s_0_dsp",
        "core.board.sequencer.step.m_0_dsp", "dut.array.receiver_1.w_2_dsp", "dut.sequencer.m_1_dsp"]}
    cells["dut.cell_0_0.lut"] = {"type": "LUT4"}
    assert dsp_units(cells) == {
        "receiver_0": ["dut.receiver_0.pq_0_p17_dsp"], "resolve": ["core.board.array.resolve.exact.s_0_dsp",
                                                                   "dut.resolve.exact.w_1_dsp"],
        "(top)": ["dut.p_0_dsp"], "shooter_2": ["core.board.array.shooter_2.pp_1_dsp"],
        "core.board.sequencer.step": ["core.board.sequencer.step.m_0_dsp"],
        "receiver_1": ["dut.array.receiver_1.w_2_dsp"], "sequencer": ["dut.sequencer.m_1_dsp"]}


def test_plan_file_and_its_errors(tmp_path):
    path = _netlist(tmp_path, {"receiver_0": 4, "shooter_0": 2})
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"58": [["receiver_0", 10], ["shooter_0", 50]]}))
    assert read_plan(plan) == {58: [("receiver_0", 10), ("shooter_0", 50)]}
    lock_dsps(path, plan)
    cells = json.loads(path.read_text())["modules"]["top"]["cells"]
    assert cells["dut.shooter_0.p1_dsp"]["attributes"]["BEL"] == site(51, 58) == "X119/Y58/MULT18_5"
    for bad, words in [({"58": [["receiver_0", 10]]}, "no row for shooter_0"),
                       ({"58": [["receiver_0", 0], ["shooter_0", 3]]}, "taken"),
                       ({"58": [["receiver_0", 0], ["shooter_0", 51]]}, "no such site"),
                       ({"57": [["receiver_0", 0], ["shooter_0", 9]]}, "not a DSP row"),
                       ({"58": [["receiver_0", 0], ["shooter_9", 9]]}, "has no multipliers"),
                       ({"58": [["receiver_0", 0], ["receiver_0", 9]]}, "twice")]:
        plan.write_text(json.dumps(bad))
        with pytest.raises(ParameterError, match=words):
            lock_dsps(_netlist(tmp_path, {"receiver_0": 4, "shooter_0": 2}), plan)
    plan.write_text("{not json")
    with pytest.raises(ParameterError, match="plan.json: not a DSP floorplan"):
        read_plan(plan)


def test_cli_refuses_a_bad_floorplan_before_any_tool(tmp_path, capsys):
    bad = tmp_path / "plan.json"
    bad.write_text("[1, 2]")
    code, err = cli(capsys, ["synth", "array", "--dsp-floorplan", str(bad), "--report", tmp_path / "r.json"])
    assert_one_line_error(code, err, "--dsp-floorplan", "not a DSP floorplan")
    code, err = cli(capsys, ["synth", "array", "--device", "25k", "--dsp-floorplan", "balanced",
                             "--report", tmp_path / "r.json"])
    assert_one_line_error(code, err, "--dsp-floorplan", "85k")
    assert not (tmp_path / "r.json").exists()
    code, err = cli(capsys, ["bitstream", "--dsp-floorplan", str(bad), "--out", tmp_path / "b.bit"])
    assert_one_line_error(code, err, "--dsp-floorplan", "not a DSP floorplan")
    assert not (tmp_path / "b.bit").exists()


@pytest.mark.synth
def test_nextpnr_places_the_multipliers_where_the_plan_locks_them(tmp_path):
    """A 1 x 2 exact array placed with ``--dsp-floorplan balanced``: nextpnr's placement has every
    MULT18X18D on the site the report's plan gives it."""
    work = tmp_path / "w"
    assert main(["synth", "array", "--rows", "1", "--cols", "2", "--bits", "6", "--no-route", "--workdir", str(work),
                 "--dsp-floorplan", "balanced", "--report", str(tmp_path / "r.json")]) == 0
    report = json.loads((tmp_path / "r.json").read_text())
    plan = {int(y): row for y, row in report["dsp_floorplan"]["rows"].items()}
    cells = next(m for m in json.loads((work / "placed.json").read_text())["modules"].values()
                 if m.get("attributes", {}).get("top"))["cells"]
    placed = {n: c["attributes"]["NEXTPNR_BEL"] for n, c in cells.items() if c["type"] == "MULT18X18D"}
    units = {}
    for name, bel in placed.items():
        units.setdefault(name.split(".")[1] if name.count(".") > 1 else "(top)", set()).add(bel)
    assert units == {unit: {site(start + i, y) for i in range(len(units[unit]))}
                     for y, row in plan.items() for unit, start in row}
    assert len(placed) == report["resources"]["dsps"] and report["processors"] == 2

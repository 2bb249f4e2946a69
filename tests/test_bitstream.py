"""``blockray bitstream``: what cannot fit is refused before any tool runs (exit 2, naming the
option); a small configuration builds a real ULX3S-85F bitstream (mark ``synth``)."""

import json
from pathlib import Path

import pytest

from blockray.host_driver.cli import main
from blockray.params import BoardParams
from blockray.synth import bitstream
from blockray.synth.nextpnr import dsp_estimate


@pytest.fixture
def no_tools(monkeypatch):
    """Any tool run fails the test: refusals must come before the tools."""
    def forbidden(*args, **kwargs):
        raise AssertionError(f"a tool ran: {args[:1]}")
    monkeypatch.setattr(bitstream, "_run", forbidden)
    monkeypatch.setattr(bitstream, "pll_config", forbidden)


@pytest.mark.parametrize("options,option", [
    (["--cell", "exact", "--rows", "4", "--cols", "4"], "--rows"),   # 408 DSPs > 156
    (["--rows", "4", "--cols", "8"], "--rows"),               # lean: 4 x 24 + 8 x 6 + 12 + 13 = 169 DSPs
    (["--patch-depth", "100000"], "--patch-depth"),           # block RAMs
    (["--voxel-depth", "1000000", "--patch-depth", "4096"], "--voxel-depth"),
    (["--baud", "7000000"], "--baud"),                        # 45 MHz / 7 Mbaud: 7.1 % off
    (["--baud", "20000000"], "--baud"),                       # fewer than 4 cycles per bit
    (["--platform", "de10-nano"], "--platform"),
    (["--bits", "30"], "--bits"),
    (["--freq", "500"], "--freq"),
    (["--cell", "lean", "--rows", "2", "--cols", "16", "--fabric-units", "cell"], "--rows"),   # 205 DSPs
    (["--cell", "lean", "--rows", "2", "--cols", "4", "--fabric-units", "cell,lut"], "--fabric-units"),
])
def test_refused_before_the_tools(options, option, no_tools, tmp_path, capsys):
    assert main(["bitstream", *options, "--out", str(tmp_path / "x.bit")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"blockray: error: {option}"), err
    assert not (tmp_path / "x.bit").exists()


def test_unwritable_output_refused(no_tools, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["bitstream", "--core", "echo", "--out", str(blocker / "x.bit")]) == 2
    assert capsys.readouterr().err.startswith("blockray: error: --out")


def test_largest_fit_fills_the_block_rams():
    p = bitstream.largest_fit(BoardParams(rows=2, cols=2, bits=16), capped=False)
    used = sum(bitstream.bram_estimate(p).values())
    assert used <= 208
    # twice the patch memory would not fit
    assert sum(bitstream.bram_estimate(p.with_(patch_depth=2 * p.patch_depth)).values()) > 208
    assert bitstream.divisor_for(60.0, 3_000_000) == 20


def test_default_memories_are_the_capped_ones():
    """The default bitstream's memories (what the host expects of it too) are the ones that meet
    the default clock, not all the block RAMs; given depths are kept."""
    p = bitstream.largest_fit(BoardParams(rows=2, cols=2, bits=16))
    assert (p.patch_depth, p.voxel_depth) == (bitstream.DEFAULT_PATCH_DEPTH, bitstream.DEFAULT_VOXEL_DEPTH)
    assert bitstream.largest_fit(BoardParams(rows=2, cols=2, bits=16), capped=False).patch_depth > p.patch_depth
    given = bitstream.largest_fit(BoardParams(rows=2, cols=2, bits=16), patch_depth=256, voxel_depth=64)
    assert (given.patch_depth, given.voxel_depth) == (256, 64)


def test_default_clock_divides_the_baud_exactly():
    """(The CLI's default clock is DEFAULT_FREQ_MHZ: test_default_board_is_the_one_that_routes.)"""
    assert bitstream.divisor_for(bitstream.DEFAULT_FREQ_MHZ, 3_000_000) * 3_000_000 == bitstream.DEFAULT_FREQ_MHZ * 1e6


@pytest.mark.synth
def test_closing_freq_is_a_pll_clock(tmp_path):
    """Below 50.5 MHz, 48 MHz would be 3 Mbaud x 16, but ecppll makes 46.875 MHz for it: 45."""
    assert bitstream.closing_freq(50.5, 3_000_000, tmp_path) == 45.0
    assert bitstream.closing_freq(61.0, 3_000_000, tmp_path) == 60.0
    assert bitstream.closing_freq(11.0, 3_000_000, tmp_path) is None


def test_timing_not_met_is_an_error(monkeypatch, tmp_path, capsys):
    """A bitstream below its clock is written but the command fails, saying what to rebuild with."""
    def built(params, **kw):
        return {"device": "LFE5U-85F", "speed_grade": "-6", "core": "board", "params": {},
                "resources": {"luts": 1}, "fits": True, "fmax_mhz": 38.2, "timing_met": False,
                "clock": {"pll_mhz": 45.0, "closing_mhz": 30.0}, "bitstream": {}}
    monkeypatch.setattr(bitstream, "build_bitstream", built)
    assert main(["bitstream", "--out", str(tmp_path / "x.bit")]) == 1
    err = capsys.readouterr().err
    assert "timing not met: Fmax 38.2 MHz at -6 is below the 45 MHz clock" in err and "--freq 30" in err


def test_default_board_is_the_one_that_routes(monkeypatch, tmp_path):
    """No options: the largest board docs/ulx3s.md routed at -6 (the lean 1 x 6, its cells on
    carry chains, the DSPs balanced, router2) with the capped memories; --cell exact: the exact
    1 x 2 with router1; each option given overrides its default, ``none`` included."""
    seen = {}

    def built(params, **kw):
        seen.update(params=params, **kw)
        return {"device": "LFE5U-85F", "speed_grade": "-6", "core": "board", "params": {}, "resources": {"luts": 1},
                "fits": True, "fmax_mhz": 63.3, "timing_met": True, "clock": {"pll_mhz": 45.0}, "bitstream": {}}
    monkeypatch.setattr(bitstream, "build_bitstream", built)

    def run(*options):
        assert main(["bitstream", *options, "--out", str(tmp_path / "x.bit")]) == 0
        return (seen["params"].rows, seen["params"].cols, seen["cell"].kind, seen["fabric_units"],
                seen["dsp_floorplan"], seen["router"])
    assert run() == (1, 6, "lean", ("cell",), "balanced", "router2")
    assert (bitstream.DEFAULT_ROWS, bitstream.DEFAULT_COLS, bitstream.DEFAULT_CELL) == (1, 6, "lean")
    p = seen["params"]
    assert (p.patch_depth, p.voxel_depth) == (bitstream.DEFAULT_PATCH_DEPTH, bitstream.DEFAULT_VOXEL_DEPTH)
    assert seen["freq"] == bitstream.DEFAULT_FREQ_MHZ
    assert run("--cell", "exact") == (1, 2, "exact", (), None, "router1")
    assert run("--rows", "2", "--cols", "2", "--cell", "exact", "--router", "router2")[:3] == (2, 2, "exact")
    assert seen["router"] == "router2"
    assert run("--fabric-units", "none", "--dsp-floorplan", "none", "--router", "router1") == (
        1, 6, "lean", (), None, "router1")
    assert run("--fabric-units", "cell,rounded", "--cols", "2")[1:4] == (2, "lean", ("cell", "rounded"))
    assert run("--core", "echo")[3:] == ((), None, "router1")           # the link alone: no array to plan


def test_lean_board_core_and_platform():
    """``--cell lean``: the board core's array is lean; the platform has the carry cells and the
    fabric units the RTL reads; the DSP estimate is the lean array's and the sequencer's (Yosys
    counted 2 more than it on a lean 2 x 16 board with carry-chain cells and row units)."""
    from blockray.cell import Cell
    from blockray.synth.nextpnr import lean_dsp_estimate
    params = BoardParams(rows=2, cols=4, bits=16, patch_depth=256, voxel_depth=64)
    for cell in (Cell("lean"), Cell()):
        core = bitstream._core("board", params, cell)
        assert core.board.cell.kind == cell.kind
        for built in (core, core.board):            # not elaborated here: no "never used" warning
            built._MustUse__silence = True
    platform = bitstream._platform("ulx3s-85f", ("cell", "rounded"))
    assert platform.ccu2c and platform.mult18x18d and platform.fabric_units == {"cell", "rounded"}
    assert bitstream._platform("ulx3s-85f").fabric_units == frozenset()
    fit = bitstream.check_fit(params.with_(cols=8), cell=Cell("lean"), fabric_units=("cell", "rounded"))
    assert fit["dsps"] == lean_dsp_estimate(16, 2, 8, ("cell", "rounded")) + 13 == 2 * 6 + 8 * 6 + 12 + 13
    assert lean_dsp_estimate(16, 2, 8, ("cell",)) == 108          # Yosys's count of the lean 2 x 8
    assert lean_dsp_estimate(16, 2, 8, ("cell", "rounded")) == 72
    assert lean_dsp_estimate(16) - lean_dsp_estimate(16, fabric_units=("exact",)) == 12     # LeanExact's


@pytest.mark.synth
def test_the_bitstreams_fabric_units_leave_no_product_to_the_dsps(tmp_path):
    """``--fabric-units exact`` (or shooter, receiver) makes the array's products generic ``$mul``
    cells; the bitstream's Yosys script turns those, and only those, into LUT multipliers, so
    synth_ecp5 cannot put them on MULT18X18D (the DSP estimate leaves them out). The
    sequencer's products stay for the DSPs."""
    import subprocess
    from amaranth.back import rtlil
    from blockray.cell import Cell
    from blockray.synth.yosys import OWN_REGISTERS, yosys_command
    assert bitstream.array_yosys_steps("top", ()) == {"script_after_read": OWN_REGISTERS.format(top="top")}
    params = BoardParams(rows=1, cols=2, bits=12, patch_depth=64, voxel_depth=16)
    platform = bitstream._platform("ulx3s-85f", ("cell", "exact"))
    (tmp_path / "core.il").write_text(rtlil.convert(bitstream._core("board", params, Cell("lean")), name="top",
                                                    platform=platform))
    script = bitstream.array_yosys_steps("top", platform.fabric_units)["script_after_read"]

    def products(then):
        out = subprocess.run(yosys_command() + ["-p", f"read_rtlil core.il; {then}; select -list t:$mul"],
                             cwd=tmp_path, capture_output=True, text=True, check=True).stdout
        return [line for line in out.splitlines() if line.startswith("top.") and "/$" in line]

    before = products("hierarchy -top top; proc")
    assert any(".array.resolve.exact" in name for name in before)         # the exact unit's, generic
    after = products(script)
    assert after and not any(".array" in name for name in after)           # the sequencer's stay
    assert any(".sequencer" in name for name in after)


@pytest.mark.synth
def test_a_failing_yosys_is_one_line_exit_2_after_the_abc_fallback(monkeypatch, tmp_path, capsys):
    """Yosys 0.70's ABC9 assert (on some netlists) is worked around with classic abc; when that
    fails too: one line naming the tool, its status, its last ERROR line and the log kept in
    ``--workdir``; exit 2, no .bit. (ecppll runs for real; Yosys is the stand-in below.)"""
    scripts = []

    def failing(cmd, workdir, log):
        scripts.append(Path(workdir, cmd[-1]).read_text())         # the .ys as each run saw it
        Path(workdir, "blockray_ulx3s.rpt").write_text("2.46.19.7. ABC_OPS_REINTEGRATE\n"
                                                      "ERROR: Assert `GetSize' failed in rtlil.cc:3091.\n")
        return 1
    monkeypatch.setattr(bitstream, "_run", failing)
    work, out = tmp_path / "w", tmp_path / "x.bit"
    assert main(["bitstream", "--core", "echo", "--out", str(out), "--workdir", str(work)]) == 2
    assert len(scripts) == 2 and "abc -lut 4" not in scripts[0] and "abc -lut 4" in scripts[1]
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"blockray: error: yosys failed (status 1): ERROR: Assert `GetSize' failed in rtlil.cc:3091.; "
                   f"log: {work / 'blockray_ulx3s.rpt'}"], err
    assert not out.exists()


@pytest.mark.synth
def test_echo_bitstream_builds(tmp_path):
    """The link's test core on the ULX3S-85F: Yosys, nextpnr-ecp5 -6, ecppack; the file is an
    ECP5 bitstream for the LFE5U-85F and the clock closes."""
    out, report_path = tmp_path / "echo.bit", tmp_path / "r.json"
    assert main(["bitstream", "--core", "echo", "--out", str(out), "--report", str(report_path)]) == 0
    data = out.read_bytes()
    assert data.startswith(b"\xff\x00") and b"LFE5U-85F-6CABGA381" in data[:64]
    assert data.find(b"\xff\xff\xbd\xb3") < 64                      # the ECP5 preamble
    assert bytes.fromhex("41113043") in data[:128]                  # LFE5U-85F IDCODE (VERIFY_ID)
    report = json.loads(report_path.read_text())
    assert report["fits"] and report["timing_met"] and report["fmax_mhz"] >= bitstream.DEFAULT_FREQ_MHZ
    assert report["speed_grade"] == "-6" and report["uart"]["divisor"] == bitstream.DEFAULT_FREQ_MHZ * 1e6 // 3_000_000
    assert report["nextpnr"]["router"] == bitstream.ROUTER == "router1"          # routes the boards (docs/ulx3s.md)
    assert report["resources"]["brams"] >= 2 and report["bitstream"]["bytes"] == len(data)


@pytest.mark.synth
@pytest.mark.slow
def test_board_bitstream_builds(tmp_path):
    """The smallest exact board (1 x 1, B = 8, small memories) with the link and, as every board
    ``blockray bitstream`` builds, the block sequencer (rays made on the board): fits, meets the
    default clock (15 MHz) at -6. Needs the board core with byte streams (issue 12)."""
    out, report_path = tmp_path / "board.bit", tmp_path / "r.json"
    assert main(["bitstream", "--cell", "exact", "--rows", "1", "--cols", "1", "--bits", "8", "--patch-depth", "256",
                 "--voxel-depth", "64", "--out", str(out), "--report", str(report_path)]) == 0
    report = json.loads(report_path.read_text())
    assert report["fits"] and report["timing_met"] and report["params"]["rays"]
    # the estimate that refuses options counts the array's products and the sequencer's
    assert report["resources"]["dsps"] == report["estimate"]["dsps"] == dsp_estimate(8) + bitstream.SEQUENCER_DSPS
    assert b"LFE5U-85F-6CABGA381" in out.read_bytes()[:64]


@pytest.mark.parametrize("limits,nextpnr,message", [
    (["dsps"], {"ran": False}, "the design does not fit the LFE5U-85F"),
    ([], {"ran": True, "returncode": -15}, "nextpnr failed with status -15"),
])
def test_failed_build_says_why(limits, nextpnr, message, monkeypatch, tmp_path, capsys):
    def built(params, **kw):
        return {"device": "LFE5U-85F", "speed_grade": "-6", "core": "board", "params": {}, "resources": {"luts": 1},
                "fits": False, "limits": limits, "nextpnr": nextpnr, "fmax_mhz": None, "timing_met": None,
                "clock": {"pll_mhz": 45.0}}
    monkeypatch.setattr(bitstream, "build_bitstream", built)
    assert main(["bitstream", "--out", str(tmp_path / "x.bit")]) == 1
    assert f"blockray: error: {message}" in capsys.readouterr().err

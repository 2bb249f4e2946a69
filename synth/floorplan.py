"""A floorplan for the multipliers: each unit's MULT18X18D locked to consecutive DSP sites, the
LFE5U-85F's three DSP rows filled evenly (``blockray synth --dsp-floorplan``).

Why: nextpnr's HeAP placer fills the middle DSP row first (the lean 2 x 8: all 52 sites at
Y = 34, 39 and 17 in the other rows), and the routing beside a full DSP row is where router2
stalls (docs/ulx3s.md, router2's heat map). With the rows filled evenly the same netlist places
with 28 % less wire (docs/synthesis.md).

    lock_dsps(netlist, plan)    write ``BEL`` attributes into a Yosys JSON netlist (nextpnr binds
                                such cells before placing), return the plan used
    balanced_plan(units)        {row: [(unit, first site), ...]}: units in order, rows filled to
                                ceil(n / 3) each, each row's units spread over its width

A *unit* is a module just below the harness (``dut.receiver_0``, ``dut.shooter_3``,
``dut.resolve``): its multipliers stay together, in the order of their names. A plan file (JSON,
``{"34": [["shooter_0", 1], ...]}``) names the row (its Y) and the first site (0 to 51, left to
right) of every unit.
"""

import json
import math
import re
from pathlib import Path

from ..errors import ParameterError

__all__ = ["DSP_ROWS", "DSP_COLUMNS", "site", "dsp_units", "balanced_plan", "read_plan", "check_floorplan", "lock_dsps"]

#: the Y of the LFE5U-85F's three rows of MULT18X18D sites
DSP_ROWS = (10, 34, 58)
#: the X of a row's 52 sites, left to right (as nextpnr named the sites it placed multipliers at)
DSP_COLUMNS = (4, 5, 8, 9, 13, 14, 17, 18, 22, 23, 26, 27, 31, 32, 35, 36, 40, 41, 44, 45, 49, 50, 53, 54,
               58, 59, 62, 63, 69, 70, 73, 74, 78, 79, 82, 83, 87, 88, 91, 92, 96, 97, 100, 101, 105, 106,
               109, 110, 114, 115, 118, 119)
FLOORPLAN_DEVICES = ("85k",)


def site(index, row):
    """The BEL name of site ``index`` (0 to 51, left to right) of DSP row ``row`` (its Y); a
    column's four BELs MULT18_0, _1, _4, _5 take the sites in turn."""
    x = DSP_COLUMNS[index]
    return f"X{x}/Y{row}/MULT18_{(0, 1, 4, 5)[index % 4]}"


def _natural(name):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def _unit_of(name):
    """The unit of a cell: the module just below the array (``...array.receiver_0``) or, outside an
    array, below the harness (``dut.sequencer``); else its module's path."""
    parts = name.split(".")[:-1]
    for root in ("array", "dut"):
        if root in parts:
            i = len(parts) - 1 - parts[::-1].index(root)
            return parts[i + 1] if i + 1 < len(parts) else "(top)"
    return ".".join(parts) or "(top)"


def dsp_units(cells):
    """{unit: [MULT18X18D cell names, sorted]} of a netlist's ``cells`` (:func:`_unit_of`: the
    harness's ``dut.receiver_0``, a board's ``core.board.array.resolve``: ``receiver_0``,
    ``resolve``; ``(top)`` for multipliers of the harnessed unit itself)."""
    units = {}
    for name, cell in cells.items():
        if cell["type"] == "MULT18X18D":
            units.setdefault(_unit_of(name), []).append(name)
    return {u: sorted(names, key=_natural) for u, names in units.items()}


def _order(units):
    """Row 0's unit first, the other units (the exact unit), the column units, the other rows'."""
    rows = sorted((u for u in units if u.startswith("receiver_")), key=_natural)
    cols = sorted((u for u in units if u.startswith("shooter_")), key=_natural)
    rest = sorted((u for u in units if u not in rows and u not in cols), key=_natural)
    return rows[:1] + rest + cols + rows[1:]


def balanced_plan(units):
    """{row: [(unit, first site)]} for ``units`` ({name: count}): in :func:`_order`, each row filled
    to the smallest capacity that takes every unit whole, a row's units spread over its 52 sites
    with equal gaps."""
    sizes = {u: len(v) if isinstance(v, (list, tuple)) else int(v) for u, v in units.items()}
    total, width = sum(sizes.values()), len(DSP_COLUMNS)
    if total > width * len(DSP_ROWS) or max(sizes.values(), default=0) > width:
        raise ParameterError(f"dsp_floorplan: {total} multipliers do not fit {len(DSP_ROWS)} rows of {width} "
                             "with each unit in one row", parameter="dsp_floorplan")
    for capacity in range(math.ceil(total / len(DSP_ROWS)), width + 1):
        rows, used = [[]], 0
        for unit in _order(sizes):
            if used + sizes[unit] > capacity:
                rows.append([])
                used = 0
            rows[-1].append(unit)
            used += sizes[unit]
        if len(rows) <= len(DSP_ROWS):
            break
    else:
        raise ParameterError(f"dsp_floorplan: the units do not fit {len(DSP_ROWS)} rows", parameter="dsp_floorplan")
    plan = {}
    for y, row in zip(DSP_ROWS, rows):
        gap = (width - sum(sizes[u] for u in row)) / (len(row) + 1)
        start, plan[y] = gap, []
        for unit in row:
            plan[y].append((unit, round(start)))
            start += sizes[unit] + gap
    return plan


def read_plan(path):
    """A plan file's ``{row: [(unit, first site)]}``; an error names the file and what is wrong."""
    try:
        raw = json.loads(Path(path).read_text())
        plan = {int(y): [(str(u), int(s)) for u, s in row] for y, row in raw.items()}
    except (OSError, ValueError, TypeError, AttributeError) as e:
        raise ParameterError(f"{path}: not a DSP floorplan ({{\"34\": [[\"unit\", first site], ...]}}): "
                             f"{str(e).splitlines()[0] if str(e) else type(e).__name__}",
                             parameter="dsp_floorplan") from None
    return plan


def _bels(plan, units, source):
    """{cell: BEL} of ``plan`` over ``units``; every unit placed once, every site in a row, none twice."""
    bels, taken, seen = {}, set(), set()
    for y, row in plan.items():
        if y not in DSP_ROWS:
            raise ParameterError(f"{source}: row {y} is not a DSP row ({', '.join(map(str, DSP_ROWS))})",
                                 parameter="dsp_floorplan")
        for unit, start in row:
            if unit not in units or unit in seen:
                raise ParameterError(f"{source}: unit {unit!r} " + ("twice" if unit in seen else
                                     f"has no multipliers (the units: {', '.join(sorted(units))})"),
                                     parameter="dsp_floorplan")
            seen.add(unit)
            for i, name in enumerate(units[unit]):
                if not 0 <= start + i < len(DSP_COLUMNS) or (y, start + i) in taken:
                    raise ParameterError(f"{source}: unit {unit!r} at row {y}, site {start + i}: "
                                         + ("taken" if (y, start + i) in taken else "no such site"),
                                         parameter="dsp_floorplan")
                taken.add((y, start + i))
                bels[name] = site(start + i, y)
    missing = sorted(set(units) - seen)
    if missing:
        raise ParameterError(f"{source}: no row for {', '.join(missing)}", parameter="dsp_floorplan")
    return bels


def check_floorplan(plan, device, target="ecp5"):
    """Refuse, before any tool runs, a ``plan`` (None, ``"balanced"`` or a plan file) that cannot
    apply: another target or part, or a file that is not a plan. Returns a plan file's
    :func:`read_plan`, else None."""
    if plan is None:
        return None
    if target != "ecp5" or device not in FLOORPLAN_DEVICES:
        raise ParameterError(f"dsp_floorplan: the DSP sites are known for the ecp5 target's "
                             f"{', '.join(FLOORPLAN_DEVICES)} only, not {target} {device}", parameter="dsp_floorplan")
    return None if plan == "balanced" else read_plan(plan)


def lock_dsps(netlist, plan="balanced", device="85k"):
    """Lock the MULT18X18D of the Yosys JSON ``netlist`` (rewritten in place) to the sites of
    ``plan`` (``"balanced"``: :func:`balanced_plan`; else a plan file, :func:`read_plan`).
    Returns the plan used and the multipliers per row."""
    layout = check_floorplan(plan, device)
    design = json.loads(Path(netlist).read_text())
    top = next(m for m in design["modules"].values() if m.get("attributes", {}).get("top"))
    units = dsp_units(top["cells"])
    layout = balanced_plan(units) if layout is None else layout
    for name, bel in _bels(layout, units, "balanced" if plan == "balanced" else plan).items():
        top["cells"][name]["attributes"]["BEL"] = bel
    Path(netlist).write_text(json.dumps(design))
    return {"plan": plan if plan == "balanced" else str(plan),
            "rows": {str(y): [[u, s] for u, s in row] for y, row in layout.items()},
            "per_row": {str(y): sum(len(units[u]) for u, _ in row) for y, row in layout.items()}}

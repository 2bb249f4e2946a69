"""Synthesis targets: the ``platform`` object the RTL's ``elaborate(self, platform)`` sees.

The RTL is target-neutral by default (``platform=None``: plain Amaranth registers and ``*``, which
any synthesis tool maps). A target object passed to ``amaranth.back.verilog.convert(...,
platform=target)`` reaches every ``elaborate`` and switches on device-specific primitives:

``ECP5Target`` (``mult18x18d = True``)  every product of :mod:`blockray.rtl.processor` is an
    ``amaranth.hdl.Instance("MULT18X18D")`` with its input and output pipeline registers on
    (``REG_INPUTA_CLK = REG_INPUTB_CLK = REG_OUTPUT_CLK = "CLK0"``), so the operand and product
    registers are inside the DSP instead of fabric flip-flops around a combinational multiplier
    (Yosys ``synth_ecp5`` never packs fabric registers into a MULT18X18D). Same latency and the
    same bits as the generic netlist; simulate it with ``synth/ecp5_mult18x18d_sim.v``.

``ECP5Target(fabric_units={"shooter"})`` keeps the products of the named array-edge units
    (``"shooter"``: the column units, ``"receiver"``: the row units) generic: fabric registers
    around a plain ``*``, which ``blockray synth`` maps to LUT multipliers (Yosys ``booth``, then
    ``synth_ecp5 -nodsp``, so only the instantiated MULT18X18Ds are DSPs). The array then needs
    18 R S (+ 24 R without the row units, + 6 S without the column units) DSPs at B = 16: a part
    whose DSP rows are too full to route (the 1 x 5 array at 92 % of the LFE5U-85F's DSPs) trades
    DSPs for LUTs. Same latency and the same bits either way. ``"cell"`` does the same for the
    processor cells' own products (exact or filtered cell), ``"exact"`` for the filtered array's
    shared exact unit (so ``cell`` alone puts the cells on LUTs and keeps the exact unit in DSPs).

The RTL reads the flags with ``getattr(platform, "mult18x18d", False)`` and
:func:`product_platform`, so any other platform object (an Amaranth vendor platform, a test's
stand-in) gets the generic netlist.

    target = target_platform("ecp5")          # or None for "generic"
    verilog.convert(Intersector(16), name="top", platform=target)
"""

from pathlib import Path

from ..errors import ParameterError
from ..rtl.platform import product_platform

__all__ = ["TARGETS", "FABRIC_UNITS", "ECP5Target", "target_platform", "product_platform", "MULT18X18D_SIM", "CCU2C_SIM"]

TARGETS = ("generic", "ecp5")

#: the units whose products :class:`ECP5Target` can leave to the fabric (LUT multipliers)
#: shooter / receiver: the column / row units; cell: the R x S cells; exact: the filtered
#: array's shared exact unit; rounded: the lean row unit's 18 products of w_k (exact w_k or from
#: m_i-bit inputs), on ECP5 as CCU2C bit heaps (rtl/lean.py; its pQ stays with ``receiver``)
FABRIC_UNITS = ("shooter", "receiver", "cell", "exact", "rounded")

#: behavioural Verilog model of the MULT18X18D configuration the RTL instantiates (Verilator)
MULT18X18D_SIM = Path(__file__).with_name("ecp5_mult18x18d_sim.v")
#: behavioural Verilog model of the CCU2C carry cell as rtl/lutdot.py instantiates it (Verilator)
CCU2C_SIM = Path(__file__).with_name("ecp5_ccu2c_sim.v")


class ECP5Target:
    """Lattice ECP5: products on registered ``MULT18X18D`` primitives (see the module doc)."""

    name = "ecp5"
    #: the flag :mod:`blockray.rtl.processor` checks: instantiate MULT18X18D with internal registers
    mult18x18d = True
    #: carry cells (``CCU2C``): the filtered and lean cells' products in the fabric
    #: (``fabric_units`` ``cell``) as bit heaps on carry chains (:mod:`blockray.rtl.lutdot`)
    ccu2c = True

    def __init__(self, fabric_units=()):
        fabric_units = frozenset(fabric_units)
        unknown = sorted(fabric_units - set(FABRIC_UNITS))
        if unknown:
            raise ParameterError(f"fabric units must be among {', '.join(FABRIC_UNITS)}, not "
                                 f"{', '.join(map(repr, unknown))}", parameter="fabric_units")
        #: units whose products stay generic (LUT multipliers after ``booth``), not MULT18X18D
        self.fabric_units = fabric_units

    def __repr__(self):
        units = ", ".join(repr(u) for u in FABRIC_UNITS if u in self.fabric_units)
        return f"ECP5Target(fabric_units={{{units}}})" if units else "ECP5Target()"


def target_platform(target, fabric_units=()):
    """The ``platform`` object for ``target`` (``"generic"`` -> None, ``"ecp5"`` ->
    ``ECP5Target(fabric_units)``; fabric units need the ECP5 target)."""
    if target not in TARGETS:
        raise ParameterError(f"target must be one of {', '.join(TARGETS)}, not {target!r}", parameter="target")
    if target != "ecp5":
        if fabric_units:
            raise ParameterError("fabric units (LUT multipliers) need the ecp5 target", parameter="fabric_units")
        return None
    return ECP5Target(fabric_units)

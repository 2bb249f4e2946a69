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

The RTL reads the flag with ``getattr(platform, "mult18x18d", False)``, so any other platform
object (an Amaranth vendor platform, a test's stand-in) gets the generic netlist.

    target = target_platform("ecp5")          # or None for "generic"
    verilog.convert(Intersector(16), name="top", platform=target)
"""

from pathlib import Path

from ..errors import ParameterError

__all__ = ["TARGETS", "ECP5Target", "target_platform", "MULT18X18D_SIM"]

TARGETS = ("generic", "ecp5")

#: behavioural Verilog model of the MULT18X18D configuration the RTL instantiates (Verilator)
MULT18X18D_SIM = Path(__file__).with_name("ecp5_mult18x18d_sim.v")


class ECP5Target:
    """Lattice ECP5: products on registered ``MULT18X18D`` primitives (see the module doc)."""

    name = "ecp5"
    #: the flag :mod:`blockray.rtl.processor` checks: instantiate MULT18X18D with internal registers
    mult18x18d = True

    def __repr__(self):
        return "ECP5Target()"


def target_platform(target):
    """The ``platform`` object for ``target`` (``"generic"`` -> None, ``"ecp5"`` -> ECP5Target)."""
    if target not in TARGETS:
        raise ParameterError(f"--target must be one of {', '.join(TARGETS)}, not {target!r}")
    return ECP5Target() if target == "ecp5" else None

"""A synthesis harness: the unit under test with its IOs replaced by logic inside the chip.

ECP5 has no out-of-context flow: every top-level port becomes an IO pin. A bare unit would use
hundreds of IOs (or not fit the package), and nextpnr leaves IO-to-register paths out of Fmax.
:class:`LfsrHarness` instead drives every input bit of the unit from on-chip registers and folds
every output bit into one pin, so all the unit's paths are register to register:

* a 32-bit maximal-length LFSR (x^32 + x^22 + x^2 + x + 1) feeds a shift register with one stage
  per input bit of the unit (each input bit is a register, its value a delayed LFSR bit: no
  input is constant, so Yosys cannot simplify the unit);
* every output bit of the unit is registered, the registers are XOR-reduced in groups of
  :data:`XOR_GROUP` bits into a second rank of registers, and those into the single output
  register ``out`` (the only pin besides ``clk`` and ``rst``).

The harness's own cost is small and known: ``inputs + 32`` FFs for the stimulus, ``outputs +
ceil(outputs / XOR_GROUP) + 1`` FFs and about ``outputs / 3`` LUTs for the reduction.
:mod:`blockray.synth.nextpnr` reports the unit's resources apart from the harness's.
"""

from amaranth.hdl import Cat, Module, Signal, Value
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

__all__ = ["LfsrHarness", "DUT_NAME", "XOR_GROUP", "unit_ports"]

#: the submodule name of the unit inside the harness (its Verilog module is ``<top>.dut``)
DUT_NAME = "dut"
#: output bits XOR-ed per first-rank register
XOR_GROUP = 24

_LFSR_WIDTH = 32
_LFSR_TAPS = (31, 21, 1, 0)          # x^32 + x^22 + x^2 + x + 1 (maximal length)


def unit_ports(component):
    """(inputs, outputs): the unit's port values as two lists (from its signature's flow)."""
    inputs, outputs = [], []
    for _path, member, value in component.signature.flatten(component):
        (inputs if member.flow == In else outputs).append(Value.cast(value))
    return inputs, outputs


class LfsrHarness(wiring.Component):
    """``component`` with LFSR-driven inputs and an XOR-reduced, registered output ``out``.

    Properties :attr:`input_bits` and :attr:`output_bits` give the unit's port widths (the
    harness's size depends on them only).
    """

    out: Out(1)

    def __init__(self, component):
        if not isinstance(component, wiring.Component):
            raise TypeError(f"the harness wraps an amaranth wiring.Component, not {component!r}")
        self._dut = component
        inputs, outputs = unit_ports(component)
        self._input_bits = sum(len(v) for v in inputs)
        self._output_bits = sum(len(v) for v in outputs)
        super().__init__()

    @property
    def input_bits(self):
        return self._input_bits

    @property
    def output_bits(self):
        return self._output_bits

    def elaborate(self, platform):
        m = Module()
        m.submodules[DUT_NAME] = dut = self._dut
        inputs, outputs = unit_ports(dut)

        lfsr = Signal(_LFSR_WIDTH, init=1)
        feedback = lfsr[_LFSR_TAPS[0]]
        for tap in _LFSR_TAPS[1:]:
            feedback = feedback ^ lfsr[tap]
        m.d.sync += lfsr.eq(Cat(feedback, lfsr[:-1]))

        if self._input_bits:
            stimulus = Signal(self._input_bits)
            m.d.sync += stimulus.eq(Cat(lfsr[-1], stimulus[:-1]))
            offset = 0
            for value in inputs:
                m.d.comb += value.eq(stimulus[offset:offset + len(value)])
                offset += len(value)

        captured = Signal(max(1, self._output_bits))
        if self._output_bits:
            m.d.sync += captured.eq(Cat(*outputs))
        groups = [captured[i:i + XOR_GROUP] for i in range(0, len(captured), XOR_GROUP)]
        rank = Signal(len(groups))
        m.d.sync += rank.eq(Cat(*(g.xor() for g in groups)))
        m.d.sync += self.out.eq(rank.xor())
        return m

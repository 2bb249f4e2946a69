"""The top level of a blockray board on a ULX3S (Lattice LFE5U-85F, speed grade -6, CABGA381).

::

    clk25 pin -> EHXPLLL -> sync clock ------------------------------+
                    | LOCK                                           |
                    +-> ResetSynchronizer -> sync reset              v
    FT231X TXD -> uart.rx --> SerialLink(core) (UART, framed link, the core) --> uart.tx -> FT231X RXD

The board clock comes from the 25 MHz oscillator through one ECP5 PLL (:class:`PLLConfig`; the
divisors are computed by ``ecppll`` in :mod:`blockray.synth.bitstream`), and the ``sync`` domain
is held in reset until the PLL locks (:class:`amaranth.lib.cdc.ResetSynchronizer`: asserted at
once, released in step with the clock). The host link is :class:`~blockray.rtl.link.SerialLink`
on the FT231X's UART pins (3 Mbaud at most). LED 0 shows the PLL locked, LED 1 a link reset
(the host's break), LED 2 the ``rx`` line's activity, LED 3 a receive FIFO overrun.
"""

from dataclasses import dataclass

from amaranth.hdl import ClockDomain, ClockSignal, Elaboratable, Instance, Module, Signal
from amaranth.lib import io
from amaranth.lib.cdc import ResetSynchronizer

from .link import SerialLink

__all__ = ["PLLConfig", "ULX3STop"]


@dataclass(frozen=True)
class PLLConfig:
    """An EHXPLLL setting: f_out = f_in * clkfb_div / clki_div (feedback from CLKOP), VCO =
    f_out * clkop_div."""
    f_in_mhz: float
    f_out_mhz: float
    clki_div: int
    clkfb_div: int
    clkop_div: int
    clkop_cphase: int
    clkop_fphase: int = 0


class ULX3STop(Elaboratable):
    """The ULX3S top level around ``core`` (any component with ``i_bytes``/``o_bytes`` byte
    streams). ``pll``: a :class:`PLLConfig` from the 25 MHz oscillator; ``divisor``: UART bit
    time in board clock cycles; ``fifo_depth``, ``payload``, ``window``: the framed link's
    (:class:`~blockray.rtl.link.SerialLink`). Elaborate with an amaranth-boards ULX3S platform."""

    def __init__(self, core, *, pll, divisor, fifo_depth=2048, payload=128, window=4):
        self.pll = pll
        self.link = SerialLink(core, divisor=divisor, fifo_depth=fifo_depth, payload=payload, window=window)

    def elaborate(self, platform):
        m = Module()
        pll = self.pll
        clk25 = platform.request("clk25", dir="-")
        m.submodules.clk25_buffer = clk25_buffer = io.Buffer("i", clk25)
        clk, locked = Signal(), Signal()
        m.submodules.pll = Instance(
            "EHXPLLL",
            a_FREQUENCY_PIN_CLKI=str(pll.f_in_mhz), a_FREQUENCY_PIN_CLKOP=str(pll.f_out_mhz),
            a_ICP_CURRENT="12", a_LPF_RESISTOR="8", a_MFG_ENABLE_FILTEROPAMP="1", a_MFG_GMCREF_SEL="2",
            p_PLLRST_ENA="DISABLED", p_INTFB_WAKE="DISABLED", p_STDBY_ENABLE="DISABLED",
            p_DPHASE_SOURCE="DISABLED", p_OUTDIVIDER_MUXA="DIVA", p_CLKOP_ENABLE="ENABLED",
            p_CLKI_DIV=pll.clki_div, p_CLKOP_DIV=pll.clkop_div, p_CLKOP_CPHASE=pll.clkop_cphase,
            p_CLKOP_FPHASE=pll.clkop_fphase, p_FEEDBK_PATH="CLKOP", p_CLKFB_DIV=pll.clkfb_div,
            i_RST=0, i_STDBY=0, i_CLKI=clk25_buffer.i, o_CLKOP=clk, i_CLKFB=clk,
            i_PHASESEL0=0, i_PHASESEL1=0, i_PHASEDIR=1, i_PHASESTEP=1, i_PHASELOADREG=1,
            i_PLLWAKESYNC=0, i_ENCLKOP=0, o_LOCK=locked)
        m.domains.sync = ClockDomain("sync")
        m.d.comb += ClockSignal("sync").eq(clk)
        platform.add_clock_constraint(clk, pll.f_out_mhz * 1e6)
        m.submodules.reset_sync = ResetSynchronizer(~locked, domain="sync")

        m.submodules.link = link = self.link
        uart = platform.request("uart", 0, dir={"rx": "-", "tx": "-", "rts": "-", "dtr": "-"})
        m.submodules.uart_rx = rx = io.Buffer("i", uart.rx)
        m.submodules.uart_tx = tx = io.Buffer("o", uart.tx)
        m.d.comb += [link.rx.eq(rx.i), tx.o.eq(link.tx)]
        for n, shown in enumerate((locked, link.link_reset, ~rx.i, link.overrun)):
            m.submodules[f"led{n}"] = led = io.Buffer("o", platform.request("led", n, dir="-"))
            m.d.comb += led.o.eq(shown)
        return m

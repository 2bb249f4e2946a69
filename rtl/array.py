"""The R x S broadcast processor array of one board.

Every cycle one patch record is broadcast to all R x S processors. Column ``s`` has a
:class:`~blockray.rtl.processor.ShooterUnit` holding shooter point P_s, row ``r`` a
:class:`~blockray.rtl.processor.ReceiverUnit` holding receiver point Q_r, and cell ``(r, s)`` a
:class:`~blockray.rtl.processor.Processor` that tests the ray P_s -> Q_r against the record and
ORs the result into its accumulator (``hit``).

The points are sampled in the cycle a record is on the array's input (the units' first stage),
so changing a point affects only the records presented after the change. ``first`` marks the
first record of a block: it travels with the record and clears the accumulators as that record's
result arrives, so blocks follow each other without a bubble.

Latency :attr:`latency` = unit latency + processor latency (4 + 4 = 8 cycles): a record presented in
cycle c is ORed into ``hit`` as seen in cycle c + latency. Throughput one record (R x S tests)
per cycle.
"""

from amaranth.hdl import Cat, Module, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.wiring import In, Out

from ..errors import ParameterError
from ..records import patch_layout, point_layout
from .processor import ArrayTiming, Processor, ReceiverUnit, ShooterUnit, _delay

__all__ = ["ProcessorArray", "broadcast_signature"]


def broadcast_signature(bits, rows, cols):
    """The inputs of an R x S array fed one broadcast patch record per cycle
    (:class:`ProcessorArray`, :class:`~blockray.rtl.filtered.FilteredArray`): ``patch``,
    ``valid``, ``first``, the R ``receivers`` and the S ``shooters`` (see
    :class:`ProcessorArray`). Each array adds its outputs to these members."""
    point = point_layout(bits)
    return wiring.Signature({
        "patch": In(patch_layout(bits)),
        "valid": In(1),
        "first": In(1),
        "receivers": In(data.ArrayLayout(point, rows)),
        "shooters": In(data.ArrayLayout(point, cols)),
    })


class ProcessorArray(wiring.Component):
    """R x S processors fed by one broadcast patch record per cycle.

    Parameters ``bits`` (B), ``rows`` (R receivers), ``cols`` (S shooter points).

    Ports
    ``patch``      In (:func:`~blockray.records.patch_layout`): the broadcast record.
    ``valid``      In: ``patch`` holds a record this cycle.
    ``first``      In: the record is its block's first (clears the accumulators on arrival).
    ``receivers``  In, R points: Q_r, sampled with each record.
    ``shooters``   In, S points: P_s, sampled with each record.
    ``hit``        Out, R * S bits: bit ``r * S + s`` is the OR of the blocked bits of ray
                   (P_s, Q_r) over the records since the last ``first``.
    ``hit_valid``  Out: a record's results arrive in ``hit`` this cycle (``valid`` delayed by
                   :attr:`latency`; for tests and monitors).
    """

    def __init__(self, bits, rows, cols):
        self._MustUse__silence = True       # no "created but never used" warning on a rejected parameter
        for name, value in (("rows", rows), ("cols", cols)):
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 64:
                raise ParameterError(f"processor array parameter {name} must be an integer from 1 to 64, "
                                     f"not {value!r}")
        self._timing = ArrayTiming(bits)       # validates bits
        self._bits, self._rows, self._cols = bits, rows, cols
        super().__init__({
            **broadcast_signature(bits, rows, cols).members,
            "hit": Out(unsigned(rows * cols)),
            "hit_valid": Out(1),
        })
        self._MustUse__silence = False

    @property
    def bits(self):
        return self._bits

    @property
    def rows(self):
        return self._rows

    @property
    def cols(self):
        return self._cols

    @property
    def latency(self):
        """Cycles from a record on the input to its results in ``hit``."""
        return self._timing.latency

    def elaborate(self, platform):
        m = Module()
        B, R, S = self._bits, self._rows, self._cols
        shooters, receivers = [], []
        for s in range(S):
            unit = ShooterUnit(B)
            m.submodules[f"shooter_{s}"] = unit
            m.d.comb += [unit.point.eq(self.shooters[s]), unit.patch.eq(self.patch), unit.valid.eq(self.valid)]
            shooters.append(unit)
        for r in range(R):
            unit = ReceiverUnit(B)
            m.submodules[f"receiver_{r}"] = unit
            m.d.comb += [unit.point.eq(self.receivers[r]), unit.patch.eq(self.patch), unit.valid.eq(self.valid)]
            receivers.append(unit)

        first = _delay(m, self.first, self._timing.unit, "first")
        hits = []
        for r in range(R):
            for s in range(S):
                cell = Processor(B)
                m.submodules[f"processor_{r}_{s}"] = cell
                m.d.comb += [
                    cell.shooter.eq(shooters[s].terms),
                    cell.receiver.eq(receivers[r].terms),
                    cell.valid.eq(shooters[s].terms_valid),
                    cell.first.eq(first),
                ]
                hits.append(cell.hit)
        m.d.comb += self.hit.eq(Cat(*hits))                 # bit r * S + s
        m.d.comb += self.hit_valid.eq(_delay(m, self.valid, self._timing.latency, "valid"))
        return m

"""A board's processor cell: which kind, and the filter's format. One frozen object, built once (the
CLI: from ``--cell`` and ``--filter-bits``) and passed whole to the RTL, the model, the harnesses,
synthesis and the board back-ends.

The kinds (docs/processor.md): ``exact`` computes the exact predicate in every cell; ``filtered``
decides most tests with the certified narrow filter (:mod:`blockray.filtered`) and hands the
undecided ones to an exact unit shared by the array; ``lean`` has the filter only, its undecided
tests leave as tags to a shared exact unit, and its w_k may come from rounded inputs
(``FilterFormat.w_input_bits``).
"""

from dataclasses import dataclass

from .errors import ParameterError
from .filtered import FilterFormat

__all__ = ["CELLS", "Cell", "check_cell"]

#: the kinds of processor cell, in the order of ``--cell``'s help
CELLS = ("exact", "filtered", "lean")


@dataclass(frozen=True)
class Cell:
    """``kind``: one of :data:`CELLS`. ``format``: the filter's
    :class:`~blockray.filtered.FilterFormat` of the filtered and lean cells; None takes the
    kind's default at the board's B (:meth:`format_at`), which may be chosen only with the scene.
    The exact cell has no filter; only the lean cell rounds w_k from its inputs."""

    kind: str = "exact"
    format: FilterFormat | None = None

    def __post_init__(self):
        if not isinstance(self.kind, str) or self.kind not in CELLS:
            raise ParameterError(f"cell must be one of {', '.join(CELLS)}, not {self.kind!r}", parameter="cell")
        f = self.format
        if f is None:
            return
        if not isinstance(f, FilterFormat):
            raise ParameterError(f"filter_bits must be a FilterFormat, not {f!r}", parameter="filter_bits")
        if not self.filtered:
            raise ParameterError(f"filter_bits sets the filter's format; it needs cell filtered or lean, "
                                 f"not {self.kind!r}", parameter="filter_bits")
        if self.kind == "filtered" and f.w_input_bits is not None:
            raise ParameterError(f"filter {f} rounds w_k from its inputs, which only the lean cell does",
                                 parameter="filter_bits")

    @property
    def filtered(self):
        """The cell filters (filtered or lean): undecided tests go to an exact unit shared by the
        array, through a hand-off whose delays depend on the data."""
        return self.kind != "exact"

    @property
    def lean(self):
        """The lean cell: the filter only, with the tags and end-point memory of rtl/lean.py."""
        return self.kind == "lean"

    def format_at(self, bits):
        """The filter's format at B = ``bits`` (None for the exact cell): :attr:`format`, or the
        kind's default. Filtered: d_k exact (B + 1 bits, at most 18) and w_k at 18 bits, one
        MULT18X18D per product. Lean: 9-bit mantissas for P - V_k (B + 1 when that is fewer: d_k
        is then exact) and for w_k, rounded from its exact value; docs/fixed-point.md measures
        1.3e-3 (cornell) and 1.9e-3 (room) undecided."""
        if self.format is not None or not self.filtered:
            return self.format
        if self.lean:
            return FilterFormat(min(9, bits + 1), 9)
        return FilterFormat(min(bits + 1, 18), 18)

    def at(self, bits):
        """This cell with its format chosen for B = ``bits``."""
        return Cell(self.kind, self.format_at(bits))

    def __str__(self):
        return self.kind if self.format is None else f"{self.kind} {self.format}"


def check_cell(cell):
    """``cell`` if it is a :class:`Cell`, else a ParameterError naming ``cell`` (a kind's name
    alone does not say the filter's format)."""
    if not isinstance(cell, Cell):
        raise ParameterError(f"cell must be a Cell (blockray.cell), not {cell!r}", parameter="cell")
    return cell

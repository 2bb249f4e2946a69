"""One top at its serial pins in a native UART harness library (sim/native/uart_harness.cpp):
the bridge of sim/uart_cocotb.py, cycle for cycle, called through ctypes with whole buffers."""

import ctypes

from . import load_library

__all__ = ["NativeUart"]

def _bind(lib):
    size, u64, u8p = ctypes.c_size_t, ctypes.c_uint64, ctypes.POINTER(ctypes.c_uint8)
    lib.bu_open.argtypes, lib.bu_open.restype = [ctypes.c_uint32], ctypes.c_void_p
    lib.bu_close.argtypes, lib.bu_close.restype = [ctypes.c_void_p], None
    lib.bu_write.argtypes, lib.bu_write.restype = [ctypes.c_void_p, ctypes.c_char_p, size], None
    lib.bu_break.argtypes, lib.bu_break.restype = [ctypes.c_void_p, ctypes.c_int], None
    lib.bu_run.argtypes = [ctypes.c_void_p, u64, u8p, size, ctypes.POINTER(size), ctypes.POINTER(u64),
                           ctypes.POINTER(size)]
    lib.bu_run.restype = None


class NativeUart:
    """The top of ``build`` (a :class:`~blockray.sim.native.NativeBuild` with
    :class:`~blockray.sim.native.UartPorts`) after its reset, ``divisor`` clock cycles per bit.
    Not thread-safe: call it from one thread."""

    CHUNK = 1 << 16

    def __init__(self, build, divisor):
        self._lib = load_library(build.library, _bind)
        self._h = self._lib.bu_open(int(divisor))

    def write(self, data):
        """Queue ``data`` for rx."""
        data = bytes(data)
        self._lib.bu_write(self._h, data, len(data))

    def brk(self, on):
        """rx held low with the queue dropped (``on``), or high again."""
        self._lib.bu_break(self._h, int(bool(on)))

    def run(self, cycles):
        """At most ``cycles`` clock cycles, less if a frame delimiter came on tx:
        ``(bytes decoded, cycles run, bytes still queued)``."""
        out, got, ran, queued = bytearray(), ctypes.c_size_t(), ctypes.c_uint64(), ctypes.c_size_t()
        buf = bytearray(self.CHUNK)
        cbuf = (ctypes.c_uint8 * self.CHUNK).from_buffer(buf)
        self._lib.bu_run(self._h, int(cycles), cbuf, self.CHUNK, ctypes.byref(got), ctypes.byref(ran), ctypes.byref(queued))
        out += buf[:got.value]
        while got.value == self.CHUNK:          # more decoded than a buffer holds: the rest, no cycles
            self._lib.bu_run(self._h, 0, cbuf, self.CHUNK, ctypes.byref(got), ctypes.byref(ctypes.c_uint64()),
                             ctypes.byref(queued))
            out += buf[:got.value]
        return bytes(out), ran.value, queued.value

    def close(self):
        if self._h:
            self._lib.bu_close(self._h)
            self._h = None

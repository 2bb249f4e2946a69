"""A stream component's vector tests in the native harness: :class:`NativeVectors` builds any
component with a stream ``i`` in and a stream ``o`` out, payloads of any width, with
sim/native/vector_harness.cpp, and runs whole buffers of payloads through it (one a cycle each
way at most), with the host timing of :mod:`blockray.sim.drive` (idle, back-pressure), seeded.
"""

import ctypes

import numpy as np

from ..drive import HostTiming
from . import NativeRunError, VectorPorts, build_native, load_library, seed_words

__all__ = ["NativeVectors", "payload_bytes"]


def payload_bytes(payload):
    """Bytes that carry a stream payload (a plain value or a ``lib.data`` view)."""
    width = len(payload.as_value()) if hasattr(payload, "as_value") else len(payload)
    return -(-width // 8)


def _bind(lib):
    d, u32, size = ctypes.c_double, ctypes.c_uint32, ctypes.c_size_t
    u8p = ctypes.POINTER(ctypes.c_uint8)
    lib.bv_open.argtypes = [ctypes.POINTER(u32), size, d, d, u32, u32, d, d, u32, u32]
    lib.bv_open.restype = ctypes.c_void_p
    lib.bv_close.argtypes = [ctypes.c_void_p]
    lib.bv_close.restype = None
    lib.bv_cycles.argtypes = [ctypes.c_void_p]
    lib.bv_cycles.restype = ctypes.c_uint64
    lib.bv_run.argtypes = [ctypes.c_void_p, ctypes.c_char_p, size, u8p, ctypes.c_uint64, ctypes.POINTER(size)]
    lib.bv_run.restype = ctypes.c_int


class NativeVectors:
    """The component ``make()`` returns, in the native vector harness, built once per design
    (cached like every native build; ``source`` as :func:`~blockray.sim.native.build_native`'s).
    :meth:`run` sends payloads as bytes and returns the outputs' bytes in order. ``patience``:
    clock cycles with nothing moving before :meth:`run` gives up."""

    def __init__(self, make, *, name, source=None, idle=HostTiming(), backpressure=HostTiming(), seed=0,
                 patience=1 << 16):
        top = make()
        self.n_in, self.n_out = payload_bytes(top.i.payload), payload_bytes(top.o.payload)
        self.build = build_native(top, name=name, source=source, ports=VectorPorts(i_bytes=self.n_in, o_bytes=self.n_out))
        top._MustUse__silence = True        # made for its widths: a cached build does not convert it
        self.patience = patience
        self._lib = load_library(self.build.library, _bind)
        key = seed_words(seed)
        self._h = self._lib.bv_open((ctypes.c_uint32 * len(key))(*key), len(key),
                                    idle.rate, idle.burst, *idle.burst_length,
                                    backpressure.rate, backpressure.burst, *backpressure.burst_length)

    def run(self, payloads):
        """The outputs of ``payloads`` ((T, n_in) uint8, least significant byte first), one
        each, in order: (T, n_out) uint8."""
        payloads = np.ascontiguousarray(payloads, dtype=np.uint8)
        if payloads.ndim != 2 or payloads.shape[1] != self.n_in:
            raise ValueError(f"payloads must be (T, {self.n_in}) bytes, not {payloads.shape}")
        out = np.zeros((len(payloads), self.n_out), dtype=np.uint8)
        got = ctypes.c_size_t()
        status = self._lib.bv_run(self._h, payloads.tobytes(), len(payloads),
                                  out.ctypes.data_as(ctypes.POINTER(ctypes.c_uint8)), self.patience, ctypes.byref(got))
        if status != 0:
            raise NativeRunError(f"the component sent {got.value} of {len(payloads)} outputs and then nothing "
                                 f"for {self.patience} cycles")
        return out

    @property
    def cycles(self):
        """Clock cycles since the component was opened (reset included)."""
        return self._lib.bv_cycles(self._h)

    def close(self):
        if self._h:
            self._lib.bv_close(self._h)
            self._h = None

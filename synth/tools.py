"""Finding the YoWASP console scripts (Yosys, nextpnr) the synth extra installs."""

import os
import shutil
import sys
from pathlib import Path

from ..extras import MissingExtra, require

__all__ = ["tool_command", "last_error"]


def tool_command(package, program, what):
    """The command of the ``package`` console script: beside the running Python first (a venv
    need not be on PATH), then on PATH, else a system ``program``. None found: MissingExtra naming
    ``what`` needs it and the install that adds it."""
    here = Path(sys.executable).parent / package
    for candidate in (str(here), shutil.which(package), shutil.which(program)):
        if candidate and os.path.exists(candidate):
            return [candidate]
    require("synth", what, only=(package,))                     # names pip install 'blockray[synth]'
    raise MissingExtra(f"no {package} program beside the installed package; reinstall it with "
                       "pip install --force-reinstall 'blockray[synth]'")


def last_error(text):
    """The line of a tool's output that says what went wrong: its last ``ERROR`` line, else its
    last line (at most 300 characters)."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return ([line for line in lines if line.startswith("ERROR")] or lines or ["no output"])[-1][:300]

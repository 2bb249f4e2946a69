"""Checks of the files a command will write, made before any long work starts.

A render or a synthesis run can take minutes; an output path that cannot be written should
stop it at once, with the option that named it, not after the work is done.

- :func:`check_output_file`: a file to be written (``--image``, ``--patches``, ``--report``,
  ``--vcd``, ``--out``). A new or existing regular file needs a folder that really accepts a new
  file (probed by creating and removing a temporary file there: this refuses ``/proc``, ``/sys``
  and read-only mounts, where permission bits alone say yes to root). An existing non-regular
  file (``/dev/null``, a pipe such as ``/dev/stdout``) must open for writing now.
- :func:`check_output_dir`: a folder to be created or filled (``synth --workdir``).
"""

import os
import stat
import tempfile

from .errors import ParameterError, printable

__all__ = ["check_output_file", "check_output_dir"]


def _error(option, path, reason):
    return ParameterError(f"{option} {printable(path, 200)}: {reason}")


def _probe_folder(folder, option, path):
    """Raise unless a new file can be created in ``folder``."""
    if not os.path.isdir(folder):
        raise _error(option, path, "cannot write: no such folder" if not os.path.exists(folder)
                     else "cannot write: the folder is not a folder")
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".blockray-probe-")
    except OSError as e:
        raise _error(option, path, f"cannot write: its folder takes no new file ({e.strerror or e})") from None
    os.close(fd)
    os.unlink(probe)


def check_output_file(path, option):
    """Raise :class:`ParameterError` (naming ``option``) unless ``path`` can be written.

    Nothing is created or changed: a probe file in the folder is removed again.
    """
    if path is None:
        return
    if str(path) == "":
        raise ParameterError(f"{option}: the file name is empty")
    path = os.fspath(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        st = None
    except OSError as e:
        raise _error(option, path, f"cannot write: {e.strerror or e}") from None
    if st is not None and stat.S_ISDIR(st.st_mode):
        raise _error(option, path, "is a folder, not a file")
    if st is not None and not stat.S_ISREG(st.st_mode):
        # a device or a pipe (/dev/null, /dev/stdout): it must take a writer now; non-blocking,
        # so a pipe without a reader is an error instead of a hang
        try:
            os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))
        except OSError as e:
            raise _error(option, path, f"cannot write: {e.strerror or e}") from None
        return
    if st is not None and not os.access(path, os.W_OK):
        raise _error(option, path, "cannot write: permission denied")
    _probe_folder(os.path.dirname(os.path.realpath(path)) or ".", option, path)


def check_output_dir(path, option):
    """Raise :class:`ParameterError` unless ``path`` is a writable folder or can be made one
    (its nearest existing ancestor is a writable folder)."""
    if path is None:
        return
    if str(path) == "":
        raise ParameterError(f"{option}: the folder name is empty")
    folder = os.path.realpath(os.fspath(path))
    if os.path.exists(folder):
        if not os.path.isdir(folder):
            raise _error(option, path, "is a file, not a folder")
        _probe_folder(folder, option, path)
        return
    ancestor = os.path.dirname(folder)
    while not os.path.exists(ancestor):
        ancestor = os.path.dirname(ancestor)
    if not os.path.isdir(ancestor):
        raise _error(option, path, f"cannot create: {printable(ancestor, 200)} is a file, not a folder")
    _probe_folder(ancestor, option, path)

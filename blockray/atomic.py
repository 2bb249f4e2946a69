"""Output files replaced atomically, alone or several together.

Every file a command writes (``render --image/--patches/--report``, ``--checkpoint``, ``synth
--report``, ``verilog --out``) goes through :class:`Outputs`: each is written to a temporary file
in its own folder (``.NAME.XXXXXXXX.tmp``), flushed and fsynced, and only when every file of the
batch is complete are they renamed over their targets (``os.replace``) and the folders fsynced.

- A write error (a full disk, a file size limit, an I/O error) raises
  :class:`~blockray.errors.ResourceError` naming the option and the file (a folder that takes no
  new file: :class:`~blockray.errors.ParameterError`); every temporary file of the batch is
  removed and no target is touched.
- A signal that ends the process while the files are written (SIGINT, or SIGTERM, which the CLI
  turns into an exception) unwinds through :meth:`Outputs.__exit__`, which removes the
  temporaries: the targets keep their previous contents. A SIGKILL can leave a ``.*.tmp`` file
  behind, never a partial target.
- The renames are the only step that is not all-or-nothing across files: each rename is atomic,
  and they run one after another only after every file is on disk (a rename on one filesystem
  does not run out of space).

A target that exists and is not a regular file (``/dev/null``, a pipe) cannot be replaced; it is
written in place. A symbolic link's target file is replaced, the link kept. A replaced file keeps
its permission bits; a new one gets ``0o666`` less the umask, as ``open`` would give it.
"""

import contextlib
import os
import signal
import stat
import tempfile
import threading

from .errors import ParameterError, ResourceError, printable

__all__ = ["Outputs", "write_file", "Terminated", "sigterm_raises"]


def _fsync(f):
    """Flush ``f`` to the disk (a hook point for the tests' signal-at-write cases)."""
    f.flush()
    os.fsync(f.fileno())


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


class Outputs:
    """A batch of files written to temporaries now and renamed over their targets together.

    Use as a context manager: :meth:`add` each file; leaving the block normally renames them all
    (:meth:`commit`), leaving it by an exception (or a signal turned into one) removes every
    temporary and leaves the targets as they were::

        with Outputs() as out:
            out.add("a.csv", "--patches", lambda f: f.write(text))
            out.add("a.png", "--image", lambda f: f.write(png), binary=True)
    """

    def __init__(self):
        self._staged = []           # (temporary, target, option)

    def add(self, path, option, write, *, binary=False):
        """Write ``path`` (named ``option`` in errors) by calling ``write(f)`` on a temporary file
        in its folder, opened for text (UTF-8, ``newline=""``) or ``binary``; fsynced, not yet
        renamed. An OSError raises :class:`ResourceError`."""
        shown = f"{option} {printable(path, 200)}"
        target = os.path.realpath(os.fspath(path))
        try:
            st = os.stat(target)
        except FileNotFoundError:
            st = None
        except OSError as e:
            raise ResourceError(f"{shown}: cannot write: {e.strerror or e}") from None
        if st is not None and not stat.S_ISREG(st.st_mode):
            self._write_in_place(target, write, binary, shown)
            return
        folder, name = os.path.split(target)
        try:
            fd, temporary = tempfile.mkstemp(dir=folder, prefix=f".{name[:100]}.", suffix=".tmp")
        except OSError as e:                    # no such folder, a read-only one: the path's fault
            raise ParameterError(f"{shown}: cannot write: {e.strerror or e}") from None
        self._staged.append((temporary, target, shown))
        try:
            os.fchmod(fd, stat.S_IMODE(st.st_mode) if st is not None else 0o666 & ~_umask())
            with (os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding="utf-8", newline="")) as f:
                write(f)
                _fsync(f)
        except OSError as e:
            raise ResourceError(f"{shown}: cannot write: {e.strerror or e}; the previous file is unchanged") \
                from None

    @staticmethod
    def _write_in_place(target, write, binary, shown):
        try:
            with open(target, "wb" if binary else "w", **({} if binary else {"newline": ""})) as f:
                write(f)
        except OSError as e:
            raise ResourceError(f"{shown}: cannot write: {e.strerror or e}") from None

    def commit(self):
        """Rename every temporary over its target, then fsync their folders."""
        folders = set()
        while self._staged:
            temporary, target, shown = self._staged[0]
            try:
                os.replace(temporary, target)
            except OSError as e:
                raise ResourceError(f"{shown}: cannot replace it: {e.strerror or e}") from None
            self._staged.pop(0)
            folders.add(os.path.dirname(target))
        for folder in folders:
            try:
                fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
            except OSError:
                continue
            try:
                os.fsync(fd)
            except OSError:
                pass                # a folder that cannot be fsynced (some network filesystems)
            finally:
                os.close(fd)

    def discard(self):
        """Remove every temporary not yet renamed."""
        while self._staged:
            temporary = self._staged.pop()[0]
            try:
                os.unlink(temporary)
            except FileNotFoundError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, kind, value, traceback):
        try:
            if kind is None:
                self.commit()
        finally:
            self.discard()
        return False


def write_file(path, option, write, *, binary=False, outputs=None):
    """Write one file atomically (:meth:`Outputs.add`), or stage it in ``outputs`` when given
    (then it is renamed with the rest of that batch)."""
    if outputs is not None:
        outputs.add(path, option, write, binary=binary)
        return
    with Outputs() as out:
        out.add(path, option, write, binary=binary)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread (:func:`sigterm_raises`) so that every ``finally`` runs
    (temporaries removed, boards and clusters closed) before the process ends."""


@contextlib.contextmanager
def sigterm_raises():
    """Within the block, SIGTERM raises :class:`Terminated` in the main thread (elsewhere, and
    after the block, the handler is left as it was)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(signum, frame):
        raise Terminated()
    previous = signal.signal(signal.SIGTERM, _raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)

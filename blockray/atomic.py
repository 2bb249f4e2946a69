"""Output files replaced atomically, alone or several together.

Every file a command writes (``render --image/--patches/--report/--vcd``, ``--checkpoint``,
``synth --report``, ``verilog --out``) goes through :class:`Outputs`: each is written to a
temporary file in its own folder (``.NAME.XXXXXXXX.tmp``), flushed and fsynced, and only when
every file of the batch is complete are they renamed over their targets (``os.replace``) and the
folders fsynced. A file that another writer opens by name (a simulator's waveform) gets the name
of its temporary from :meth:`Outputs.reserve`.

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


def _fsync_file(path, shown):
    """Flush a file another writer wrote and closed to the disk."""
    try:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as e:
        raise ResourceError(f"{shown}: cannot write: {e.strerror or e}; the previous file is unchanged") from None


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
        self._staged = []           # (temporary, target, option and path, written here)

    def add(self, path, option, write, *, binary=False):
        """Write ``path`` (named ``option`` in errors) by calling ``write(f)`` on a temporary file
        in its folder, opened for text (UTF-8, ``newline=""``) or ``binary``; fsynced, not yet
        renamed. An OSError raises :class:`ResourceError`."""
        shown = f"{option} {printable(path, 200)}"
        target, st = self._target(path, shown)
        if st is not None and not stat.S_ISREG(st.st_mode):
            self._write_in_place(target, write, binary, shown)
            return
        fd = self._stage(target, st, shown, written_by_us=True)
        try:
            with (os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding="utf-8", newline="")) as f:
                write(f)
                _fsync(f)
        except OSError as e:
            raise ResourceError(f"{shown}: cannot write: {e.strerror or e}; the previous file is unchanged") \
                from None

    def reserve(self, path, option):
        """The name of a temporary file in ``path``'s folder for a writer that opens it by name
        itself (a simulator writing a waveform); :meth:`commit` fsyncs it and renames it over
        ``path`` with the batch, :meth:`discard` removes it. A ``path`` that exists and is not a
        regular file is returned as it is (written in place)."""
        shown = f"{option} {printable(path, 200)}"
        target, st = self._target(path, shown)
        if st is not None and not stat.S_ISREG(st.st_mode):
            return target
        os.close(self._stage(target, st, shown, written_by_us=False))
        return self._staged[-1][0]

    @staticmethod
    def _target(path, shown):
        """The file ``path`` names (a symbolic link followed) and its ``os.stat`` (None: new)."""
        target = os.path.realpath(os.fspath(path))
        try:
            return target, os.stat(target)
        except FileNotFoundError:
            return target, None
        except OSError as e:
            raise ResourceError(f"{shown}: cannot write: {e.strerror or e}") from None

    def _stage(self, target, st, shown, *, written_by_us):
        """A new temporary beside ``target`` with its permission bits, staged; returns its fd."""
        folder, name = os.path.split(target)
        try:
            fd, temporary = tempfile.mkstemp(dir=folder, prefix=f".{name[:100]}.", suffix=".tmp")
        except OSError as e:                    # no such folder, a read-only one: the path's fault
            raise ParameterError(f"{shown}: cannot write: {e.strerror or e}") from None
        self._staged.append((temporary, target, shown, written_by_us))
        try:
            os.fchmod(fd, stat.S_IMODE(st.st_mode) if st is not None else 0o666 & ~_umask())
        except OSError as e:
            os.close(fd)
            raise ResourceError(f"{shown}: cannot write: {e.strerror or e}") from None
        return fd

    @staticmethod
    def _write_in_place(target, write, binary, shown):
        try:
            with open(target, "wb" if binary else "w", **({} if binary else {"newline": ""})) as f:
                write(f)
        except OSError as e:
            raise ResourceError(f"{shown}: cannot write: {e.strerror or e}") from None

    def commit(self):
        """Fsync the reserved files (:meth:`reserve`), rename every temporary over its target,
        then fsync their folders."""
        for temporary, _, shown, written_by_us in self._staged:
            if not written_by_us:
                _fsync_file(temporary, shown)
        folders = set()
        while self._staged:
            temporary, target, shown, _ = self._staged[0]
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

"""Atomic outputs (blockray/atomic.py): a failed write, a full disk or a signal during the write
leaves the previous files as they were, and a render's image, CSV and report are replaced together."""

import contextlib
import os
import signal
import stat
import subprocess
import sys
import textwrap
import time

import pytest

from blockray.atomic import Outputs, write_file
from blockray.errors import ParameterError, ResourceError

#: the render of every CLI case here: a few seconds
RENDER = ["render", "cornell", "--max-edge", "300", "--max-shots", "5", "--samples", "2", "--size", "48", "--quiet"]
OUTPUTS = {"--image": "out.png", "--patches": "out.csv", "--report": "out.json"}
OLD = {option: f"old {option} contents\n".encode() for option in OUTPUTS}


def _old_outputs(folder):
    for option, name in OUTPUTS.items():
        (folder / name).write_bytes(OLD[option])
    return [a for option, name in OUTPUTS.items() for a in (option, str(folder / name))]


def _assert_old_and_no_temporaries(folder):
    for option, name in OUTPUTS.items():
        assert (folder / name).read_bytes() == OLD[option], f"{name} was changed"
    left = [p.name for p in folder.iterdir() if p.name.endswith(".tmp")]
    assert not left, left


def _temporaries(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_a_batch_is_renamed_together_or_not_at_all(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("old a")
    b.write_text("old b")

    def broken(f):
        f.write("half of b")
        raise OSError(5, "Input/output error")
    with pytest.raises(ResourceError, match=r"^--b .*b\.txt: cannot write: Input/output error; the previous file is"):
        with Outputs() as out:
            out.add(a, "--a", lambda f: f.write("new a"))
            assert a.read_text() == "old a"           # nothing is renamed before the batch ends
            out.add(b, "--b", broken)
    assert (a.read_text(), b.read_text()) == ("old a", "old b")
    assert _temporaries(tmp_path) == []
    with pytest.raises(RuntimeError):               # any exception, e.g. from the render between adds
        with Outputs() as out:
            out.add(a, "--a", lambda f: f.write("new a"))
            raise RuntimeError
    assert a.read_text() == "old a" and _temporaries(tmp_path) == []
    with Outputs() as out:
        out.add(a, "--a", lambda f: f.write("new a"))
        out.add(b, "--b", lambda f: f.write(b"new b"), binary=True)
    assert (a.read_text(), b.read_text()) == ("new a", "new b")
    assert _temporaries(tmp_path) == []


def test_modes_links_and_devices(tmp_path):
    old = os.umask(0o022)
    try:
        new = tmp_path / "new.txt"
        write_file(new, "--x", lambda f: f.write("x"))
        assert stat.S_IMODE(new.stat().st_mode) == 0o644          # as open() would make it
    finally:
        os.umask(old)
    kept = tmp_path / "kept.txt"
    kept.write_text("old")
    kept.chmod(0o600)
    write_file(kept, "--x", lambda f: f.write("new"))
    assert stat.S_IMODE(kept.stat().st_mode) == 0o600 and kept.read_text() == "new"
    link = tmp_path / "link.txt"
    link.symlink_to(kept)
    write_file(link, "--x", lambda f: f.write("through the link"))
    assert link.is_symlink() and kept.read_text() == "through the link"
    write_file("/dev/null", "--x", lambda f: f.write("gone"))      # written in place, not replaced
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)
    with pytest.raises(ParameterError, match=r"^--x .*/no/such/x\.txt: cannot write: No such file"):
        write_file(tmp_path / "no" / "such" / "x.txt", "--x", lambda f: f.write("x"))


# --- a full disk ---------------------------------------------------------------------------

#: runs the CLI with RLIMIT_FSIZE set once the first output is written, after the render (so
#: numba's cache is not limited); SIGXFSZ ignored, a write past the limit fails with EFBIG as one
#: on a full disk with ENOSPC
_LIMITED = textwrap.dedent("""
    import resource, signal, sys
    from blockray import atomic
    from blockray.host_driver.cli import main
    limit = int(sys.argv[1])
    add = atomic.Outputs.add

    def limited(self, *args, **kwargs):
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
        return add(self, *args, **kwargs)
    if limit:
        atomic.Outputs.add = limited
    sys.exit(main(sys.argv[2:]))
""")


@contextlib.contextmanager
def _small_disk(folder, disk):
    """``(folder, limit)``: a 32 KiB tmpfs mounted on ``folder`` (limit 0), or ``folder`` itself
    and a 12 kB file size limit (the old files take 3 of the tmpfs's 8 pages, the image 1)."""
    folder.mkdir()
    if disk == "rlimit":
        yield folder, 12_000
        return
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=32k", "tmpfs", str(folder)],
                      capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here (not root, or no CAP_SYS_ADMIN); the rlimit case runs anyway")
    try:
        yield folder, 0
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=True)


@pytest.mark.parametrize("disk", ["rlimit", "tmpfs"])
def test_full_disk_is_one_line_exit_2_and_no_output_changes(tmp_path, disk):
    """The CSV (~17 kB; the image and report are ~3 kB) does not fit:
    exit 2 naming it, and the old image and report are not replaced either (all or nothing)."""
    with _small_disk(tmp_path / "disk", disk) as (folder, limit):
        argv = RENDER + _old_outputs(folder)
        done = subprocess.run([sys.executable, "-c", _LIMITED, str(limit), *argv], cwd=folder,
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 2, done.stderr
        err = done.stderr.strip().splitlines()
        assert len(err) == 1 and "Traceback" not in done.stderr, done.stderr
        assert err[0].startswith("blockray: error: --patches ") and "out.csv: cannot write: " in err[0], err
        assert ("File too large" if disk == "rlimit" else "No space left on device") in err[0], err
        _assert_old_and_no_temporaries(folder)


# --- a signal during the write ----------------------------------------------------------------

#: runs the CLI with a hook in the write path: after ``--option``'s file is written (not yet
#: fsynced or renamed) it says so in READY and blocks opening the FIFO, where the signal finds it
_HOOKED = textwrap.dedent("""
    import os, signal, sys
    # SIGINT as a terminal delivers it: a shell starts background jobs (a CI script's, say) with
    # SIGINT ignored, and the child would inherit that
    signal.signal(signal.SIGINT, signal.default_int_handler)
    from blockray import atomic
    from blockray.host_driver.cli import main
    option, ready, fifo = sys.argv[1:4]
    add = atomic.Outputs.add

    def hooked(self, path, opt, write, **kw):
        def blocking(f):
            write(f)
            if opt == option:
                f.flush()
                open(ready, "w").close()
                open(fifo).read()           # no writer ever opens it
        return add(self, path, opt, blocking, **kw)
    atomic.Outputs.add = hooked
    sys.exit(main(sys.argv[4:]))
""")


@pytest.mark.parametrize("option, sig", [("--image", signal.SIGTERM), ("--patches", signal.SIGINT),
                                         ("--report", signal.SIGTERM)])
def test_signal_during_the_write_leaves_the_old_files(tmp_path, option, sig):
    folder = tmp_path / "out"
    folder.mkdir()
    argv = RENDER + _old_outputs(folder)
    ready, fifo = tmp_path / "ready", tmp_path / "fifo"
    os.mkfifo(fifo)
    proc = subprocess.Popen([sys.executable, "-c", _HOOKED, option, str(ready), str(fifo), *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while not ready.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert ready.exists(), proc.communicate(timeout=60)
        name = OUTPUTS[option]
        staged = [p for p in _temporaries(folder) if p.startswith(f".{name}.")]
        assert len(staged) == 1, _temporaries(folder)        # caught in the middle of writing it
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == (143 if sig == signal.SIGTERM else 130), err
    assert err.strip() == ("blockray: terminated" if sig == signal.SIGTERM else "blockray: interrupted"), err
    _assert_old_and_no_temporaries(folder)
    assert _temporaries(folder) == []


@pytest.mark.parametrize("ending", ["error", "SIGTERM"])
def test_vcd_is_replaced_with_the_outputs_or_left_as_it_was(tmp_path, capsys, monkeypatch, ending):
    """--vcd: each board's simulator writes its waveform (FILE, FILE.1) to a temporary beside it,
    renamed with the render's other outputs. A render that fails, or gets SIGTERM, while the
    waveforms are being written leaves the previous files (tests/test_rtl_board.py: a render that succeeds writes
    them, and leaves no temporary)."""
    from blockray.host_driver.cli import main
    from blockray.host_driver.board.simulated import AmaranthTransport
    from blockray.host_driver.board.transport import TransportError
    from scenes import RTL_BITS, room_scene
    room_scene(tmp_path, 1.5)
    vcd, csv = tmp_path / "w.vcd", tmp_path / "w.csv"
    old = {vcd: "old board 0 waveform\n", tmp_path / "w.vcd.1": "old board 1 waveform\n", csv: "old csv\n"}
    for path, text in old.items():
        path.write_text(text)
    argv = ["render", str(tmp_path / "room.obj"), "--max-edge", "1.5", "--voxels", "3", "--samples", "4",
            "--max-shots", "1", "--rows", "2", "--cols", "2", "--boards", "2", "--bits", str(RTL_BITS),
            "--board", "amaranth", "--vcd", str(vcd), "--patches", str(csv), "--quiet"]
    recv, calls, written = AmaranthTransport.recv, [], []

    def failing(self, count, **kw):
        data = recv(self, count, **kw)
        calls.append(count)
        if len(calls) == 2:             # each board has answered once (IDENTIFY)
            written.extend(p.stat().st_size for p in tmp_path.iterdir() if p.name.startswith(".w.vcd."))
            if ending == "SIGTERM":
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(10)                  # the CLI's handler raises here
            raise TransportError("injected: the link failed")
        return data
    monkeypatch.setattr(AmaranthTransport, "recv", failing)
    code, line = (2, "blockray: error: injected: the link failed") if ending == "error" else \
        (143, "blockray: terminated")
    assert main(argv) == code
    assert line in capsys.readouterr().err
    assert len(written) == 2 and all(written), written      # both waveforms had begun, beside w.vcd
    assert {path: path.read_text() for path in old} == old
    assert _temporaries(tmp_path) == []

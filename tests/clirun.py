"""Running the CLI in the tests' process and checking its one-line errors (imported as ``clirun``)."""

import json

from blockray.host_driver.cli import main


def cli(capsys, argv):
    """Exit status and stderr of ``blockray argv``; the error part must be one line."""
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    if code == 2:
        errors = [line for line in err.splitlines() if line.startswith("blockray: error: ")]
        assert len(errors) == 1, err
        assert all(line.startswith("blockray: ") for line in err.splitlines()), err
    return code, err


def assert_one_line_error(code, err, *needles):
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.startswith("blockray: error: ")]
    assert len(lines) == 1, err
    for needle in needles:
        assert needle in lines[0], lines[0]


def faulty_render(room, tmp_path, args, rate, seed):
    """Render ``room`` (its OBJ path and fault-free CSV) with ``args`` at ``rate`` faults per byte:
    the CSV must be the fault-free one byte for byte; returns the report's ``link_integrity``."""
    path, clean = room
    csv, report = tmp_path / "p.csv", tmp_path / "r.json"
    assert main(["render", str(path), *args, "--patches", str(csv), "--report", str(report),
                 "--link-faults", str(rate), "--link-seed", str(seed)]) == 0
    integrity = json.loads(report.read_text())["link_integrity"]
    print("rate", rate, "seed", seed, integrity)
    assert csv.read_bytes() == clean
    return integrity


def room_render(folder, args, *extra):
    """The small room of tests/scenes.py in ``folder`` and its CSV rendered with ``args``
    (then ``extra``): ``(path, csv bytes)``, the ``room`` of :func:`faulty_render`."""
    from scenes import room_obj
    path = room_obj(folder)
    out = path.parent / "clean.csv"
    assert main(["render", str(path), *args, *extra, "--patches", str(out)]) == 0
    return path, out.read_bytes()


def hopeless_render(capsys, room, tmp_path, args, where):
    """At 0.05 faults per byte the render ends with exit 2 and one error line naming ``where``
    (after the scene's quantisation warning, if any), no traceback and no CSV."""
    path, _ = room
    csv = tmp_path / "p.csv"
    assert main(["render", str(path), *args, "--patches", str(csv), "--link-faults", "0.05"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    err = [line for line in lines if not line.startswith("blockray: warning:")]
    assert len(err) == 1 and f"{where}: the link failed" in err[0] and "last fault: " in err[0], lines
    assert not any("Traceback" in line for line in lines)
    assert not csv.exists()

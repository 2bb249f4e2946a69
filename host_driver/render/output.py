"""Writers for --patches (CSV) and --report (JSON). Neither writes a non-finite number: the
render stops a diverging solve first (host_driver/radiosity/solver.py), and these refuse one before
writing anything. Both write atomically (:mod:`blockray.atomic`): alone, or staged in the
render's batch of outputs (``outputs``), renamed together with the image."""

import csv
import json
import math

import numpy as np

from ...atomic import write_file
from ...errors import SolveError, option, printable

__all__ = ["write_patches_csv", "write_report_json"]

PATCH_COLUMNS = ["patch", "group", "area", "cx", "cy", "cz", "B_r", "B_g", "B_b"]


def write_patches_csv(path, scene, radiosity, outputs=None):
    """One row per patch: ``patch,group,area,cx,cy,cz,B_r,B_g,B_b``."""
    bad = np.flatnonzero(~np.isfinite(radiosity).all(axis=1))
    if len(bad):
        i = int(bad[0])
        raise SolveError(f"{option('patches')} {printable(path, 200)}: patch {i}'s radiosity is {np.asarray(radiosity[i]).tolist()}; "
                         f"not written", patch=i)

    def write(f):
        w = csv.writer(f)
        w.writerow(PATCH_COLUMNS)
        c = scene.centroids
        for i in range(scene.patches):
            g = scene.group_names[scene.group[i]] if scene.group_names else str(scene.group[i])
            w.writerow([i, g, repr(float(scene.areas[i])), *(repr(float(x)) for x in c[i]),
                        *(repr(float(x)) for x in radiosity[i])])
    write_file(path, "--patches", write, outputs=outputs)


def _plain(x):
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.floating):
        return float(x)
    return x


def _non_finite(x, key="report"):
    """The key path of the first non-finite number in the plain value ``x``, or None."""
    if isinstance(x, float) and not math.isfinite(x):
        return key
    items = x.items() if isinstance(x, dict) else enumerate(x) if isinstance(x, list) else ()
    for k, v in items:
        found = _non_finite(v, f"{key}[{k!r}]")
        if found:
            return found
    return None


def write_report_json(path, report, outputs=None):
    plain = _plain(report)
    bad = _non_finite(plain)
    if bad:
        raise SolveError(f"{option('report')} {printable(path, 200)}: {bad} is not a finite number; not written")

    def write(f):
        json.dump(plain, f, indent=2, sort_keys=False, allow_nan=False)
        f.write("\n")
    write_file(path, "--report", write, outputs=outputs)

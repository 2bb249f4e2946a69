"""Writers for --patches (CSV) and --report (JSON)."""

import csv
import json

import numpy as np

from ..errors import ParameterError

__all__ = ["write_patches_csv", "write_report_json"]

PATCH_COLUMNS = ["patch", "group", "area", "cx", "cy", "cz", "B_r", "B_g", "B_b"]


def _open(path, option):
    try:
        return open(path, "w", newline="")
    except OSError as e:
        raise ParameterError(f"{option} {path}: cannot write: {e.strerror}") from None


def write_patches_csv(path, scene, radiosity):
    """One row per patch: ``patch,group,area,cx,cy,cz,B_r,B_g,B_b``."""
    with _open(path, "--patches") as f:
        w = csv.writer(f)
        w.writerow(PATCH_COLUMNS)
        c = scene.centroids
        for i in range(scene.patches):
            g = scene.group_names[scene.group[i]] if scene.group_names else str(scene.group[i])
            w.writerow([i, g, repr(float(scene.areas[i])), *(repr(float(x)) for x in c[i]),
                        *(repr(float(x)) for x in radiosity[i])])


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


def write_report_json(path, report):
    with _open(path, "--report") as f:
        json.dump(_plain(report), f, indent=2, sort_keys=False)
        f.write("\n")

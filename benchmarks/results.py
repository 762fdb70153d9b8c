"""Where benchmark numbers go: docs/benchmarks/<name>.json, written atomically."""
from __future__ import annotations

import json
import os

FOLDER = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "docs", "benchmarks")


def path(name: str) -> str:
    return os.path.join(FOLDER, name + ".json")


def write(name: str, data: dict) -> str:
    """Write ``data`` to docs/benchmarks/<name>.json via a temporary file and a rename."""
    out = path(name)
    os.makedirs(FOLDER, exist_ok=True)
    with open(out + ".tmp", "w") as fh:
        json.dump(data, fh, indent=1)
        fh.write("\n")
    os.replace(out + ".tmp", out)
    return out


def crossing(gamma, y, level: float) -> float:
    """gamma where y first reaches ``level`` (log-linear interpolation between the two steps
    around it), independent of where the last step happened to land."""
    import numpy as np
    ly = np.log(np.asarray(y, dtype=float))
    k = int(np.argmax(ly >= np.log(level)))
    return float(gamma[k - 1] + (np.log(level) - ly[k - 1]) * (gamma[k] - gamma[k - 1]) / (ly[k] - ly[k - 1]))

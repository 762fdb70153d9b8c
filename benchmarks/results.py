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

"""A run file read into memory as the post-run fits and the figures use it (``Run``), through
``io.RunFile``: the attributes, the scene, the time series cut to a common length, and the
analysis instants, each tagged with the direction, leg and row of its time-series row."""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, field

import numpy as np

from ..io import RunFile


@dataclass
class Run:
    """The parts of a run file that the fits and figures use, read into memory."""
    path: str
    attrs: dict
    model: str
    model_attrs: dict
    scene: dict
    ts: dict                                        # name -> 1-D array
    analysis: list = field(default_factory=list)    # dicts: attrs + arrays + "direction"

    def param(self, name, default=None):
        """A [model] parameter of the scene (e.g. mu, N)."""
        return self.scene.get("model", {}).get(name, default)


def load(path: str) -> Run:
    """The run file ``path`` as a :class:`Run` (InputError from ``io.RunFile`` if it is not
    one)."""
    with RunFile(path) as rf:
        attrs = rf.attrs
        try:
            scene = tomllib.loads(rf.scene_text)
        except tomllib.TOMLDecodeError:
            scene = {}
        model = rf.model or str(scene.get("model", {}).get("name", ""))
        model_attrs, ts, analysis = rf.model_attrs, rf.timeseries(), rf.analyses()
    if "step" in ts and len(ts["step"]):          # tag each instant with its row
        steps = ts["step"]
        for a in analysis:
            rows = np.nonzero(steps == a["step"])[0]
            if rows.size:
                r = rows[-1]
                a.setdefault("direction", int(ts["direction"][r]) if "direction" in ts else 1)
                a.setdefault("leg", int(ts["leg"][r]) if "leg" in ts else 0)
                a["row"] = int(r)
    return Run(path, attrs, model, model_attrs, scene, ts, analysis)

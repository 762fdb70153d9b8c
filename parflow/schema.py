"""Scene sections as dataclasses: each key is declared once, where the code that uses it
lives, with its type, default, range check and one line of documentation.

    @dataclass
    class OutputOptions:
        path: str = key("out/run.h5", lambda v: len(v) > 0, "a non-empty path", "the run file")

:func:`table` turns such a dataclass into the scene's schema table {key: Key}; ``scene``
assembles the schema from the section classes (``dynamics.heun.StepControl`` is
[integrator], ``algebra.solvers.SolverOptions`` [solver], ``io.OutputOptions`` [output],
``protocol.ObservablesOptions`` [observables], ``protocol.ProtocolOptions`` [protocol],
``protocol.LegRule`` a [[protocol.leg]]); a model's ``PARAMS`` table has the same shape.
tests/test_scene_docs.py holds docs/scenes.md against it.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple


class Key(NamedTuple):
    """One scene key: its type, default (None: no default), range check and its text."""
    type: type
    default: Any
    check: Callable | None = None
    allowed: str = ""
    doc: str = ""


def key(default, check: Callable | None = None, allowed: str = "", doc: str = ""):
    """A dataclass field that is a scene key (the metadata :func:`table` reads)."""
    return dataclasses.field(default=default, metadata=dict(check=check, allowed=allowed, doc=doc))


POSITIVE = (lambda v: v > 0, "> 0")
NON_NEGATIVE = (lambda v: v >= 0, ">= 0")

_TYPES = {"float": float, "int": int, "str": str, "bool": bool, "list": list, "dict": dict}


def table(cls) -> dict[str, Key]:
    """{key: Key} of a section dataclass, in declaration order."""
    out = {}
    for f in dataclasses.fields(cls):
        typ = _TYPES[f.type] if isinstance(f.type, str) else f.type
        m = f.metadata
        out[f.name] = Key(typ, f.default if f.default is not dataclasses.MISSING else None,
                          m.get("check"), m.get("allowed", ""), m.get("doc", ""))
    return out


def from_params(params: dict) -> dict[str, Key]:
    """A model's PARAMS {name: (type, default, check, description)} as {key: Key}."""
    return {k: Key(t, d, c, desc, desc) for k, (t, d, c, desc) in params.items()}


def defaults(cls) -> dict:
    """{key: default} of a section dataclass."""
    return {k: v.default for k, v in table(cls).items()}

"""Scenes: the whole description of a run, as TOML (docs/scenes.md).

``load_scene(text)`` parses, fills defaults and validates; every error is an
:class:`InputError` naming the key, what was wrong and what is allowed.
"""
from __future__ import annotations

import copy
import difflib
import math
import re
import tomllib

from .algebra.solvers import PARALLEL_FACTORS, PRESETS
from .dynamics.bonded import REUSE_FACTOR
from .dynamics.heun import CONTROLLERS, StepControl
from .models import MODELS, check_memory, get_model
from .state import InputError

DEFAULT_SCENE = """\
# parflow default scene: a rigid chain in planar extension (paper Fig. 2, mu = 0),
# driven forward until <V^2> = 1e8 (close to jamming), then reversed (buckling).
title = "chain N=10000, eps=0.1, mu=0: forward to <V^2>=1e8, then reverse"
seed = 1

[model]
name = "chain"
N = 10000
epsilon = 0.1
mu = 0

[[protocol.leg]]
direction = "forward"
V2_above = 1e8

[[protocol.leg]]
direction = "reverse"
strain = 0.02
V2_below = 1.0

[observables]
analysis_quantity = "V2"
analysis_per_decade = 2

[output]
path = "out/default.h5"
"""

_POS = (lambda v: v > 0, "> 0")
_NONNEG = (lambda v: v >= 0, ">= 0")

# section -> key -> (type, default, (check, allowed-text) or None)
SCHEMA = {
    "": {
        "title": (str, "", None),
        "seed": (int, 1, _NONNEG),
    },
    "protocol": {
        "max_steps": (int, 1_000_000, _POS),
        "leg": (list, None, None),
    },
    "integrator": {
        "tol": (float, 0.05, (lambda v: 0 < v < 1, "in (0, 1)")),
        "max_displacement": (float, 0.05, _POS),
        "max_dgamma": (float, 1e-2, _POS),
        "min_dgamma": (float, 1e-14, _POS),
        "initial_dgamma": (float, 1e-4, _POS),
        "length_tol": (float, 1e-12, _POS),
        "controller": (str, "I", (lambda v: v in CONTROLLERS, f"one of {list(CONTROLLERS)}")),
    },
    "observables": {
        "omega_min_every": (int, 0, _NONNEG),
        "n_eigs": (int, 1, _POS),
        "analysis_quantity": (str, "V2", (lambda v: v in ("V2", "sigma"), "'V2' or 'sigma'")),
        "analysis_per_decade": (float, 0.0, _NONNEG),
        "analysis_every": (int, 0, _NONNEG),
        "analysis_strain": (float, 0.0, _NONNEG),
        "analysis_from_strain": (float, 0.0, _NONNEG),
        "snapshot_every": (int, 0, _NONNEG),
    },
    "solver": {
        "preset": (str, "direct", (lambda v: v in PRESETS, f"one of {sorted(PRESETS)}")),
        "parallel": (str, "auto", (lambda v: v in PARALLEL_FACTORS, f"one of {list(PARALLEL_FACTORS)}")),
        "reuse_factor": (str, "auto", (lambda v: v in REUSE_FACTOR, f"one of {list(REUSE_FACTOR)}")),
    },
    "output": {
        "path": (str, "out/run.h5", (lambda v: len(v) > 0, "a non-empty path")),
        "flush_seconds": (float, 30.0, _POS),
        "checkpoint_every": (int, 500, _POS),
        "checkpoint_minutes": (float, 5.0, _POS),
        "progress_seconds": (float, 2.0, _POS),
    },
}
# step-control presets (the speed/accuracy trade; measured in docs/benchmarks.md)
INTEGRATOR_PRESETS = {
    "fast": dict(tol=0.2, max_displacement=0.2),
    "default": dict(tol=0.05, max_displacement=0.05),
    "tight": dict(tol=0.01, max_displacement=0.01),
}

LEG = {
    "direction": (str, None, (lambda v: v in ("forward", "reverse"), "'forward' or 'reverse'")),
    "sigma_above": (float, None, _POS),
    "sigma_below": (float, None, _POS),
    "V2_above": (float, None, _POS),
    "V2_below": (float, None, _POS),
    "strain": (float, None, _POS),
    "max_steps": (int, None, _POS),
}
STOP_KEYS = ("sigma_above", "sigma_below", "V2_above", "V2_below", "strain", "max_steps")
SECTIONS = ("model", "protocol", "integrator", "observables", "solver", "output", "petsc")


def _unknown(key: str, allowed, where: str) -> InputError:
    close = difflib.get_close_matches(key, list(allowed), n=1)
    hint = f"; did you mean {close[0]!r}?" if close else f"; allowed: {', '.join(sorted(allowed))}"
    return InputError(f"unknown key {where}{key!r}{hint}")


def _typed(value, typ, name):
    if typ is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if typ is int and isinstance(value, float) and value.is_integer() and abs(value) < 2**53:
        value = int(value)
    if typ in (int, float) and isinstance(value, bool) or not isinstance(value, typ):
        raise InputError(f"{name} must be of type {typ.__name__}, got {value!r} "
                         f"({type(value).__name__})")
    if typ is float and not math.isfinite(value):
        raise InputError(f"{name} must be finite, got {value!r}")
    return value


def _fill(table: dict, schema: dict, where: str) -> dict:
    out = {}
    for key in table:
        if key not in schema:
            raise _unknown(key, schema, where)
    for key, (typ, default, check) in schema.items():
        if key not in table:
            if default is not None:
                out[key] = default
            continue
        value = _typed(table[key], typ, f"{where}{key}")
        if check is not None and not check[0](value):
            raise InputError(f"{where}{key} = {value!r} is out of range: must be {check[1]}")
        out[key] = value
    return out


def load_scene(text: str, source: str = "<scene>") -> dict:
    """Parse and validate a scene; returns a dict with every default filled in."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{source}: malformed TOML: {exc}") from None
    except RecursionError:
        raise InputError(f"{source}: malformed TOML: arrays or tables nested too deeply") from None
    top = {k: v for k, v in raw.items() if not isinstance(v, dict)}
    for key, value in raw.items():
        if isinstance(value, dict) and key not in SECTIONS:
            raise _unknown(key, SECTIONS, "section ")
    if not isinstance(raw.get("model"), dict):
        raise InputError(f"{source}: the scene has no [model] table: add one naming the model "
                         f"and its size, e.g. [model] name = \"chain\", N = 1000 "
                         f"(models: {', '.join(MODELS)}; python -m parflow.shear --print-scene "
                         f"shows a whole scene)")
    scene = _fill(top, SCHEMA[""], "")
    for section in SECTIONS:
        table = raw.get(section, {})
        if not isinstance(table, dict):
            raise InputError(f"[{section}] must be a table")
        if section == "model":
            scene["model"] = _model(table)
        elif section == "petsc":
            scene["petsc"] = _petsc(table)
        elif section == "integrator":
            table = dict(table)
            preset = table.pop("preset", "default")
            if preset not in INTEGRATOR_PRESETS:
                raise InputError(f"integrator.preset must be one of {list(INTEGRATOR_PRESETS)}, "
                                 f"got {preset!r}")
            scene["integrator_preset"] = preset
            scene["integrator"] = _fill({**INTEGRATOR_PRESETS[preset], **table},
                                        SCHEMA["integrator"], "integrator.")
        else:
            scene[section] = _fill(table, SCHEMA[section], f"{section}.")
    scene["protocol"]["leg"] = _legs(raw.get("protocol", {}).get("leg"))
    StepControl(**scene["integrator"]).validate()      # the integrator's own cross-checks
    scene["text"] = text
    return scene


def _model(table: dict) -> dict:
    if "name" not in table:
        raise InputError(f"model.name is missing: name the model, one of {list(MODELS)}")
    name = table["name"]
    if not isinstance(name, str):
        raise InputError(f"model.name must be a string, one of {list(MODELS)}")
    model = get_model(name)
    schema = {"name": (str, name, None)}
    for key, (typ, default, check, desc) in model.PARAMS.items():
        schema[key] = (typ, default, None if check is None else (check, desc))
    return _fill(table, schema, "model.")


def _petsc(table: dict) -> dict:
    out = {}
    for key, value in table.items():
        if isinstance(value, dict):
            raise InputError(f"petsc.{key}: PETSc options are flat: write "
                             f"{key}_<option> = value")
        if not isinstance(value, (str, int, float, bool)):
            raise InputError(f"petsc.{key} must be a string, number or boolean")
        name = key.lstrip("-")
        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", name):
            raise InputError(f"petsc.{key!r}: a PETSc option name is letters, digits and '_', "
                             f"without spaces (e.g. tau_pc_factor_mat_solver_type)")
        if isinstance(value, str) and (re.search(r"\s|\x00", value) or value.startswith("-")):
            raise InputError(f"petsc.{name} = {value!r}: an option value is one word "
                             f"(no spaces, not starting with '-'); give each option its own key")
        if isinstance(value, float) and not math.isfinite(value):
            raise InputError(f"petsc.{name} = {value!r} must be finite")
        out[name] = value
    return out


def _legs(legs) -> list:
    if legs is None:
        raise InputError("the scene has no protocol: add at least one [[protocol.leg]] with "
                         "direction = 'forward' and a stop rule (e.g. V2_above = 1e8)")
    if not isinstance(legs, list) or not all(isinstance(x, dict) for x in legs):
        raise InputError("protocol.leg must be an array of tables ([[protocol.leg]])")
    out = []
    for k, leg in enumerate(legs):
        where = f"protocol.leg[{k}]."
        if "direction" not in leg:
            raise InputError(f"{where}direction is missing: 'forward' or 'reverse'")
        leg = _fill(leg, LEG, where)
        if not any(key in leg for key in STOP_KEYS):
            raise InputError(f"{where[:-1]} has no stop rule: give one of {', '.join(STOP_KEYS)}")
        out.append(leg)
    return out


def check_resources(scene: dict, n_ranks: int = 1, ranks_here: int | None = None) -> None:
    """InputError if the scene's model is too large for this machine's memory on ``n_ranks``
    ranks (``ranks_here`` of them on this machine): an estimate from measured bytes per rod /
    particle / disc (``models.MEMORY``), checked before anything is allocated.  Reads the
    machine, so call it on one rank (``errors.collective``), unlike load_scene."""
    check_memory(scene["model"]["name"], scene["model"], n_ranks, ranks_here,
                 scene.get("solver", {}).get("parallel", "auto"))


# what --set may change when a run is restarted: how it is integrated, solved and written,
# not what is simulated
RESTART_SETTABLE = ("integrator", "solver", "output")


def apply_settings(scene: dict, settings: list[str], restart: bool = False, branch: bool = False) -> dict:
    """A copy of ``scene`` with ``SECTION.KEY=VALUE`` settings applied (``--set``), each
    validated as if it were in the scene file (VALUE is read as TOML, else as a string).
    A leg's stop rule is ``protocol.leg.K.KEY=VALUE`` (K from 0).  On a restart only the
    sections of RESTART_SETTABLE can change (and not output.path); a branch (a restart into
    a new file) may also change the protocol."""
    scene = copy.deepcopy(scene)
    settable = RESTART_SETTABLE + (("protocol",) if branch else ())
    for item in settings:
        key, sep, text = item.partition("=")
        section, dot, name = key.strip().partition(".")
        if not sep or not dot or not name:
            raise InputError(f"--set {item!r}: write SECTION.KEY=VALUE, e.g. integrator.controller=PI")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        if restart and (section not in settable or (section, name) == ("output", "path")):
            raise InputError(f"--set {key}: a restart continues the same simulation; it can "
                             f"change {', '.join(s + '.*' for s in settable)} "
                             f"(not output.path)" + ("" if branch else "; to change the protocol, "
                                                      "branch the run into a new file (--output)"))
        if section == "protocol" and name.startswith("leg."):
            _set_leg(scene, key.strip(), name, value)
            continue
        if section in ("model", "petsc"):
            raise InputError(f"--set {key}: [{section}] is not settable from the command line: "
                             f"edit the scene file" + (" (PETSc options: -name value)" if section == "petsc" else ""))
        if section not in SCHEMA or section == "":
            raise _unknown(section, [s for s in SECTIONS if s in SCHEMA], "--set section ")
        if section == "integrator" and name == "preset":
            raise InputError("--set integrator.preset: set the preset's keys instead "
                             "(integrator.tol, integrator.max_displacement)")
        where = f"{section}."
        if name not in SCHEMA[section]:
            raise _unknown(name, SCHEMA[section], where)
        scene[section] = _fill({**scene[section], name: value}, SCHEMA[section], where)
    StepControl(**scene["integrator"]).validate()      # the integrator's own cross-checks
    scene["settings"] = list(scene.get("settings", [])) + list(settings)
    return scene


def _set_leg(scene: dict, key: str, name: str, value) -> None:
    """protocol.leg.K.KEY=VALUE: one key of leg K, validated like the scene's legs."""
    parts = name.split(".")
    legs = scene["protocol"]["leg"]
    if len(parts) != 3 or not parts[1].isdigit() or int(parts[1]) >= len(legs):
        raise InputError(f"--set {key}: write protocol.leg.K.KEY=VALUE with K in 0..{len(legs) - 1}")
    k, leg_key = int(parts[1]), parts[2]
    where = f"protocol.leg[{k}]."
    if leg_key not in LEG:
        raise _unknown(leg_key, LEG, where)
    legs[k] = _fill({**legs[k], leg_key: value}, LEG, where)


def with_overrides(scene: dict, output: str | None = None) -> dict:
    scene = copy.deepcopy(scene)
    if output:
        scene["output"]["path"] = output
    return scene

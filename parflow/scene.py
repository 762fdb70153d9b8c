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

from dataclasses import dataclass

from .algebra.solvers import SolverOptions
from .dynamics.heun import StepControl
from .io import OutputOptions
from .models import MODELS, check_memory, get_model
from .protocol import STOP_KEYS, LegRule, ObservablesOptions, ProtocolOptions
from .schema import NON_NEGATIVE, Key, from_params, table
from .schema import key as _key
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

@dataclass
class SceneOptions:
    """The scene's top-level keys (``schema``)."""
    title: str = _key("", None, "", "free text")
    seed: int = _key(1, *NON_NEGATIVE, "same seed, same result")


@dataclass
class EnsembleOptions:
    """The scene's [ensemble] table (``schema``): many samples of the scene in one job
    (``parflow.ensemble``, docs/ensembles.md).  Here, not in ensemble.py: the schema sits
    below the run (layer 5)."""
    samples: int = _key(0, lambda v: 0 <= v <= 10**6, "0 .. 1000000", "samples of the scene "
                        "in one job (0: one run, no ensemble); --samples K overrides")
    ranks_per_sample: int = _key(1, lambda v: v > 0, "> 0", "ranks of each sample's group "
                                 "(the job's ranks must be a multiple); --ranks-per-sample overrides")


# section -> key -> schema.Key(type, default, check, allowed, doc): each section's keys are
# declared once, by the dataclass of the code that uses them
SCHEMA = {
    "": table(SceneOptions),
    "protocol": table(ProtocolOptions),
    "integrator": table(StepControl),
    "observables": table(ObservablesOptions),
    "solver": table(SolverOptions),
    "output": table(OutputOptions),
    "ensemble": table(EnsembleOptions),
}
# step-control presets (the speed/accuracy trade; measured in docs/benchmarks.md): the keys
# they set; "default" is StepControl's own defaults
INTEGRATOR_PRESETS = {
    "fast": dict(tol=0.2, max_displacement=0.2),
    "default": {},
    "tight": dict(tol=0.01, max_displacement=0.01),
}

LEG = table(LegRule)
SECTIONS = ("model", "protocol", "integrator", "observables", "solver", "output", "ensemble",
            "petsc")


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
    for name, k in schema.items():
        if name not in table:
            if k.default is not None:
                out[name] = k.default
            continue
        value = _typed(table[name], k.type, f"{where}{name}")
        if k.check is not None and not k.check(value):
            raise InputError(f"{where}{name} = {value!r} is out of range: must be {k.allowed}")
        out[name] = value
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
    _check_leg_integrators(scene)
    scene["text"] = text
    return scene


def _model(table: dict) -> dict:
    if "name" not in table:
        raise InputError(f"model.name is missing: name the model, one of {list(MODELS)}")
    name = table["name"]
    if not isinstance(name, str):
        raise InputError(f"model.name must be a string, one of {list(MODELS)}")
    model = get_model(name)
    schema = {"name": Key(str, name), **from_params(model.PARAMS)}
    return _fill(table, schema, "model.")


def _flatten_petsc(table: dict, prefix: str = "") -> dict:
    """Nested tables name a prefix: [petsc.tau] ksp_type = "cg" is tau_ksp_type = "cg" (a
    table per solver, e.g. [petsc.tau], [petsc.spec], [petsc.contact])."""
    out = {}
    for key, value in table.items():
        name = f"{prefix}{key.lstrip('-')}"
        if isinstance(value, dict):
            for k, v in _flatten_petsc(value, name + "_").items():
                if k in out:
                    raise InputError(f"petsc.{k} is given twice (flat and in a nested table)")
                out[k] = v
        elif name in out:
            raise InputError(f"petsc.{name} is given twice (flat and in a nested table)")
        else:
            out[name] = value
    return out


def _petsc(table: dict) -> dict:
    out = {}
    for key, value in _flatten_petsc(table).items():
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


def _check_leg_integrators(scene: dict) -> None:
    """A leg's ``integrator`` table: [integrator] keys (no preset), typed and range-checked as
    there, merged over the scene's and cross-checked; it and ``perturb`` only for the bonded
    models."""
    bonded = get_model(scene["model"]["name"]).ENGINE == "bonded"
    for k, leg in enumerate(scene["protocol"]["leg"]):
        if leg.get("perturb") and not bonded:
            raise InputError(f"protocol.leg[{k}].perturb: only for bonded models (chain, "
                             f"network): a displaced {scene['model']['name']} would overlap")
        if "integrator" not in leg:
            continue
        where = f"protocol.leg[{k}].integrator."
        if not bonded:
            raise InputError(f"{where[:-1]}: the {scene['model']['name']} model has no "
                             "integrator (its step is controlled by [model] keys); remove it")
        if "preset" in leg["integrator"]:
            raise InputError(f"{where}preset: a leg takes the preset's keys, not a preset "
                             "(e.g. tol, max_displacement)")
        given = {n: v for n, v in _fill(leg["integrator"], SCHEMA["integrator"], where).items()
                 if n in leg["integrator"]}
        leg["integrator"] = given
        try:
            StepControl(**{**scene["integrator"], **given}).validate()
        except InputError as exc:
            raise InputError(f"protocol.leg[{k}]: {exc}") from None


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
    _check_leg_integrators(scene)
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

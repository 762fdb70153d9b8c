"""Model builders.  Each model module provides PARAMS (schema of its [model] table),
FLOW, build(params, seed) -> State, observables(state, F) -> dict and
analyses(system, state, F) -> dict(arrays=..., scalars=...).  A model with
ENGINE = "contacts" (suspension) is stepped by engines.ContactEngine instead and provides
the hooks that engine calls (controls, restore_dict, analyses(comm, state, F, scene, dir))."""
from importlib import import_module

MODELS = ("chain", "network", "suspension")


def get_model(name: str):
    from ..state import InputError
    if name not in MODELS:
        raise InputError(f"model.name must be one of {list(MODELS)}, got {name!r}")
    return import_module(f".{name}", __name__)

"""The contract every model keeps: one module under ``parflow/models/``, registered in
``models.MODELS``, with these names (checked by :func:`check_contract` and, for every
registered model, by tests/test_contract.py).

    NAME          str: the scene's ``model.name``
    ENGINE        "bonded" (persistent rods: Heun steps of N tau = -b) or "contacts"
                  (hard discs: one contact LCP per step)
    FLOW          "shear" or "extension": the velocity gradient E of the affine flow
    PARAMS        {key: (type, default, check, description)}: the scene's [model] table
    FACTOR_REUSE  bool: the bonded engine may reuse a step's factor for its last force solve
    build(params, seed) -> State
                  the initial state (params: the validated [model] table)
    observables(state, F) -> dict
                  per-step scalars merged into the time-series row (F: the engine's forces)
    analyses(at: state.Instant) -> dict(arrays=..., scalars=...)
                  what is measured at the instants the scene's schedule picks
    omega_min     None (the engine computes omega_min = sqrt(lambda_min(N)) on its own force
                  factor: bonded models) or a function (at: Instant) -> float (the contact
                  engine asks the model: the suspension's is that of its frozen contacts)

A model's parameters reach its code through the scene (``at.scene["model"]``, ``params`` of
``build``); ``State.meta`` records what was built (it is written to the run file's /model
attributes) but is not a channel for settings.
"""
from __future__ import annotations

ENGINES = ("bonded", "contacts")
FLOWS = ("shear", "extension")
REQUIRED = ("NAME", "ENGINE", "FLOW", "PARAMS", "FACTOR_REUSE", "build", "observables",
            "analyses", "omega_min")


def check_contract(module) -> None:
    """TypeError naming what a model module lacks or gets wrong."""
    missing = [k for k in REQUIRED if not hasattr(module, k)]
    if missing:
        raise TypeError(f"model {getattr(module, '__name__', module)} lacks {', '.join(missing)}")
    if module.ENGINE not in ENGINES:
        raise TypeError(f"model {getattr(module, '__name__', getattr(module, 'NAME', '?'))}: ENGINE = {module.ENGINE!r}, not one of {ENGINES}")
    if module.FLOW not in FLOWS:
        raise TypeError(f"model {getattr(module, '__name__', getattr(module, 'NAME', '?'))}: FLOW = {module.FLOW!r}, not one of {FLOWS}")
    for k in ("build", "observables", "analyses"):
        if not callable(getattr(module, k)):
            raise TypeError(f"model {getattr(module, '__name__', getattr(module, 'NAME', '?'))}: {k} is not callable")
    if module.omega_min is not None and not callable(module.omega_min):
        raise TypeError(f"model {getattr(module, '__name__', getattr(module, 'NAME', '?'))}: omega_min must be None or callable")
    for key, spec in module.PARAMS.items():
        if not (isinstance(spec, tuple) and len(spec) == 4 and isinstance(spec[3], str)):
            raise TypeError(f"model {getattr(module, '__name__', getattr(module, 'NAME', '?'))}: PARAMS[{key!r}] is not "
                            f"(type, default, check, description)")

"""What a restart reads from a run file, and the checks it passes first.

``check_checkpoint`` refuses, with one line naming the file and the inconsistency, a
checkpoint that does not belong to its file: missing groups or attributes, non-finite
numbers, shapes that do not fit the initial state, an engine other than the file's model's,
rods off their lengths, counts that disagree with the time series, a leg outside the scene.
It runs on rank 0 before anything touches the file (``Run`` raises its InputError on every
rank), so a refused restart leaves the file as it was.
"""
from __future__ import annotations

import h5py
import numpy as np

from .errors import InputError
from .geometry import cell_at, pair_vectors
from .io import RunFile
from .models import MODELS, get_model


def read_checkpoint(path: str, n_legs: int, model: str):
    """(initial state arrays, checkpoint attrs and arrays, /model attrs) of a run file, after
    :func:`check_checkpoint`: on rank 0, before anything touches the file."""
    with RunFile(path) as run:
        check_checkpoint(run.h5, path, n_legs, model)
        return run.initial(), run.checkpoint(), dict(run.h5["model"].attrs) if "model" in run.h5 else {}


# What a restart reads from /checkpoint (attrs; arrays in _CK_ARRAYS), per engine: the
# driver's loop counters (Run.execute) and each engine's own state (engines.*.checkpoint()
# and what their restore reads).  Optional keys have defaults in the code that reads them.
_CK_INT = ("step", "leg", "leg_steps", "n_rows", "level", "strain_mark", "steps", "collisions",
           "singular_events", "infeasible_reductions", "direction")
_CK_DRIVER = ("step", "strain", "leg", "leg_strain", "leg_steps", "n_rows", "level")
_CK_ENGINE = {"bonded": ("gamma", "dgamma"),
              "contacts": ("gamma", "sigma", "vmax", "steps", "collisions", "max_overlap",
                           "singular_events", "infeasible_reductions")}
_CK_ARRAYS = {"bonded": ("s",), "contacts": ("s", "active_keys")}
# keys only one engine writes: a checkpoint holding them was written by that engine
_CK_MARKS = {"bonded": ("tau", "err_prev"), "contacts": ("active_keys", "vmax", "collisions")}
_ROD_TOL = 1e-6     # largest relative rod-length error of a bonded checkpoint (runs: ~1e-12)


def check_checkpoint(f, path: str, n_legs: int | None = None, model: str | None = None) -> None:
    """Refuse (InputError, one line naming the file and the inconsistency) a checkpoint that
    a restart could not continue from correctly: missing group or attributes, non-numeric or
    non-finite values, arrays whose shapes do not match the file's initial state, a
    checkpoint of the other engine than the file's model runs on, rods not at their rest
    lengths (positions of another run), counters that disagree with the time series
    (``n_rows`` rows, the ``step`` column at row n_rows - 1), a leg index outside the
    scene's legs.  ``f`` is the open run file; nothing is written.  Called before the
    restart touches the file, hence "the file was not changed"."""
    def bad(what: str):
        raise InputError(f"{path!r}: cannot restart from its checkpoint: {what}; the file was not changed")

    if not isinstance(f.get("checkpoint"), h5py.Group):
        raise InputError(f"{path!r} has no checkpoint: it cannot be restarted; the file was not changed")
    for g in ("initial", "timeseries"):
        if not isinstance(f.get(g), h5py.Group):
            bad(f"the file has no /{g} group")
    name = _text(f.attrs.get("model", ""))
    if name not in MODELS:
        bad(f"the file's model attribute is {name!r}, not one of {list(MODELS)}")
    if model is not None and model != name:
        bad(f"the file's model is {name!r} but its scene's is {model!r}")
    kind = get_model(name).ENGINE
    if "engine" in f.attrs and _text(f.attrs["engine"]) != kind:
        bad(f"the file's engine attribute is {_text(f.attrs['engine'])!r} but model {name!r} "
            f"runs on the {kind!r} engine")
    g = f["checkpoint"]
    keys = set(g.attrs) | set(g)
    other = "contacts" if kind == "bonded" else "bonded"
    marks = [k for k in _CK_MARKS[other] if k in keys]
    if marks:
        bad(f"the checkpoint was written by the {other} engine (it has {', '.join(marks)}), "
            f"but model {name!r} runs on the {kind} engine: it belongs to another run")
    missing = [k for k in _CK_DRIVER + _CK_ENGINE[kind] if k not in g.attrs] + \
              [f"/checkpoint/{k}" for k in _CK_ARRAYS[kind] if not isinstance(g.get(k), h5py.Dataset)]
    if missing:
        bad(f"the checkpoint has no {', '.join(missing)}")

    # attributes: numeric scalars, integers where counted, finite
    ck = {}
    for k, v in g.attrs.items():
        if k not in _CK_DRIVER + _CK_ENGINE[kind] + _CK_INT + ("err_prev",):
            continue
        a = np.asarray(v)
        if a.ndim != 0 or not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
            bad(f"checkpoint attribute {k} = {v!r} is not a number")
        x = a.item()
        if k in _CK_INT:
            if not (np.issubdtype(a.dtype, np.integer) or (np.isfinite(x) and float(x).is_integer())):
                bad(f"checkpoint attribute {k} = {x!r} is not an integer")
            x = int(x)
        elif k != "err_prev" and not np.isfinite(x):      # err_prev: NaN = no previous step
            bad(f"checkpoint attribute {k} = {x!r} is not finite")
        ck[k] = x

    # the initial state the checkpoint continues
    ini = f["initial"]
    init = {}
    for k in ("s", "h0", "E") + (("radii",) if kind == "contacts" else ()):
        if not isinstance(ini.get(k), h5py.Dataset):
            bad(f"the file has no /initial/{k}")
        init[k] = _numeric(ini[k], f"/initial/{k}", bad)
    s0 = init["s"]
    if s0.ndim != 2 or s0.shape[0] < 1 or s0.shape[1] < 2:
        bad(f"/initial/s has shape {s0.shape}, not (N, d)")
    n, d = s0.shape
    for k in ("h0", "E"):
        if init[k].shape != (d, d):
            bad(f"/initial/{k} has shape {init[k].shape}, not {(d, d)} (d = {d})")
    s = _numeric(g["s"], "/checkpoint/s", bad)
    if s.shape != s0.shape:
        bad(f"/checkpoint/s has shape {s.shape} but /initial/s has {s0.shape} "
            f"(N = {n}, d = {d}): the checkpoint belongs to another system")

    # counters against each other, the scene and the time series
    step, n_rows = ck["step"], ck["n_rows"]
    if step < 0 or ck["leg_steps"] < 0 or ck["leg_steps"] > step:
        bad(f"step = {step}, leg_steps = {ck['leg_steps']}: need 0 <= leg_steps <= step")
    if ck["strain"] < 0 or ck["leg_strain"] < 0 or ck["leg_strain"] > ck["strain"] * (1 + 1e-9) + 1e-300:
        bad(f"strain = {ck['strain']:g}, leg_strain = {ck['leg_strain']:g}: need "
            f"0 <= leg_strain <= strain")
    if ck["leg"] < 0 or (n_legs is not None and ck["leg"] > n_legs):
        bad(f"leg = {ck['leg']} but the scene has {n_legs} leg(s) (0..{n_legs} allowed)"
            if n_legs is not None else f"leg = {ck['leg']} is negative")
    ts = f["timeseries"]
    if not isinstance(ts.get("step"), h5py.Dataset):
        bad("the time series has no step column")
    n_ts = ts["step"].shape[0] if ts["step"].ndim == 1 else -1
    if n_rows < 1 or n_rows > n_ts:
        bad(f"n_rows = {n_rows} but the time series has {n_ts} row(s)")
    short = [q for q in ts if not isinstance(ts[q], h5py.Dataset) or ts[q].ndim != 1
             or ts[q].shape[0] < n_rows]
    if short:
        bad(f"time-series column(s) {', '.join(short)} have fewer than n_rows = {n_rows} rows")
    row = _numeric(ts["step"], "/timeseries/step", bad, finite=False)[n_rows - 1]
    if row != step:
        bad(f"step = {step} but the time series' step at row n_rows - 1 = {n_rows - 1} is "
            f"{row:g}: the checkpoint belongs to another run")
    if "gamma" in ts:
        g_row = float(ts["gamma"][n_rows - 1])
        if not np.isclose(g_row, ck["gamma"], rtol=1e-12, atol=1e-14):
            bad(f"gamma = {ck['gamma']:.10g} but the time series' gamma at row {n_rows - 1} is "
                f"{g_row:.10g}: the checkpoint belongs to another run")

    if kind == "bonded":
        _check_bonded_checkpoint(f, g, ck, init, s, bad)
    else:
        _check_contacts_checkpoint(g, ck, init, s, bad)


def _check_bonded_checkpoint(f, g, ck, init, s, bad) -> None:
    n, d = s.shape
    if not ck["dgamma"] > 0:
        bad(f"dgamma = {ck['dgamma']:g}: the next strain step must be > 0")
    bg = f["initial"].get("bonds")
    if not isinstance(bg, h5py.Group) or any(not isinstance(bg.get(k), h5py.Dataset)
                                              for k in ("i", "j", "shift", "l0")):
        bad("the file has no /initial/bonds (i, j, shift, l0)")
    i, j = (_numeric(bg[k], f"/initial/bonds/{k}", bad) for k in ("i", "j"))
    shift, l0 = _numeric(bg["shift"], "/initial/bonds/shift", bad), _numeric(bg["l0"], "/initial/bonds/l0", bad)
    nc = i.shape[0] if i.ndim == 1 else -1
    if not (j.shape == l0.shape == (nc,) and shift.shape == (nc, d)) or \
            not (np.issubdtype(i.dtype, np.integer) and np.issubdtype(j.dtype, np.integer)):
        bad(f"/initial/bonds: i {i.shape}, j {j.shape}, shift {shift.shape}, l0 {l0.shape} "
            f"are not Nc integer pairs, (Nc, {d}) shifts and Nc lengths")
    if nc and (min(i.min(), j.min()) < 0 or max(i.max(), j.max()) >= n):
        bad(f"/initial/bonds index a node outside 0..{n - 1}")
    if "tau" in g:
        tau = _numeric(g["tau"], "/checkpoint/tau", bad)
        if tau.shape != (nc,):
            bad(f"/checkpoint/tau has shape {tau.shape} but the file has {nc} rods: "
                f"the checkpoint belongs to another system")
    if nc:
        r = pair_vectors(s, cell_at(init["h0"], init["E"], ck["gamma"]), i, j, shift)
        err = np.abs(np.sqrt(np.einsum("ad,ad->a", r, r)) - l0) / np.maximum(l0, 1e-300)
        if not err.max() <= _ROD_TOL:
            a = int(np.argmax(err))
            bad(f"its positions do not keep this file's rods at their lengths (rod {a}: "
                f"relative error {err[a]:.3g} > {_ROD_TOL:g} at gamma = {ck['gamma']:.10g}): "
                f"the checkpoint belongs to another run")


def _check_contacts_checkpoint(g, ck, init, s, bad) -> None:
    n = s.shape[0]
    radii = init["radii"]
    if radii.shape != (n,) or not np.all(radii > 0):
        bad(f"/initial/radii has shape {radii.shape} (need ({n},), every radius > 0)")
    keys = _numeric(g["active_keys"], "/checkpoint/active_keys", bad)
    if keys.ndim != 1 or (keys.size and (not np.issubdtype(keys.dtype, np.integer)
                                         or keys.min() < 0 or keys.max() >= n * n)):
        bad(f"/checkpoint/active_keys are not contact keys i N + j of N = {n} discs")
    if ck.get("dgamma", 0.0) < 0:
        bad(f"dgamma = {ck['dgamma']:g} < 0")
    if "phi" in g.attrs:                # a run that compresses while it shears
        phi = np.asarray(g.attrs["phi"])
        if phi.ndim != 0 or not np.issubdtype(phi.dtype, np.floating) or not 0 < float(phi) < 1:
            bad(f"checkpoint attribute phi = {g.attrs['phi']!r} is not a packing fraction in (0, 1)")
    for k in ("sigma", "vmax", "max_overlap", "collisions", "singular_events", "infeasible_reductions"):
        if ck[k] < 0:
            bad(f"{k} = {ck[k]:g} < 0")
    if ck.get("direction", 1) not in (1, -1):
        bad(f"direction = {ck['direction']} (must be +1 or -1)")
    if ck["steps"] != ck["step"]:
        bad(f"the suspension's step count {ck['steps']} differs from the run's step = {ck['step']}: "
            f"the checkpoint belongs to another run")


def _numeric(ds, where: str, bad, finite: bool = True) -> np.ndarray:
    a = ds[()]
    if not isinstance(a, np.ndarray):
        a = np.asarray(a)
    if not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
        bad(f"{where} holds {a.dtype} data, not numbers")
    if finite and np.issubdtype(a.dtype, np.floating) and not np.all(np.isfinite(a)):
        bad(f"{where} has {int(np.count_nonzero(~np.isfinite(a)))} non-finite value(s) "
            f"(NaN or inf)")
    return a


def _text(v) -> str:
    return v.decode(errors="replace") if isinstance(v, bytes) else str(v)

"""The step loop: scene -> model -> State -> legs of adaptive steps -> HDF5 (DESIGN §3).

Every rank runs the same loop on replicated geometry; PETSc distributes the algebra; rank 0
alone writes the file and prints.
"""
from __future__ import annotations

import logging
import math
import os
import subprocess
import sys
import time

import numpy as np
from petsc4py import PETSc

from . import __version__
from .cli import collective
from .dynamics.engines import _at, make_engine  # noqa: F401  (_at: used by tests and analyses)
from .dynamics.heun import Jammed, StepControl
from .io import RunWriter, WriteError, collective_write, load_group, read_run
from .models import get_model
from .solvers import SolveError, unused_options
from .state import STOPS, Bonds, InputError, State, Terminated

log = logging.getLogger("parflow")


def setup_logging(comm, quiet: bool) -> None:
    log.handlers.clear()
    log.propagate = False
    if comm.getRank() == 0 and not quiet:
        h = logging.StreamHandler(sys.stderr)
        h.setFormatter(logging.Formatter("[parflow] %(message)s"))
        log.addHandler(h)
        log.setLevel(logging.INFO)
    else:
        log.addHandler(logging.NullHandler())


def git_commit() -> str:
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        out = subprocess.run(["git", "-C", here, "rev-parse", "HEAD"], capture_output=True,
                             text=True, timeout=5)
        dirty = subprocess.run(["git", "-C", here, "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5).stdout.strip()
        return out.stdout.strip() + ("-dirty" if dirty else "") if out.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def versions() -> str:
    import h5py
    import scipy
    from mpi4py import MPI
    v = dict(parflow=__version__, python=sys.version.split()[0], numpy=np.__version__,
             scipy=scipy.__version__, h5py=h5py.__version__,
             petsc=".".join(map(str, PETSc.Sys.getVersion())), mpi=MPI.Get_library_version().split("\n")[0])
    try:   # the package version only: importing slepc4py.SLEPc would initialise SLEPc
        import slepc4py   # on this rank alone and make the ranks' finalisation diverge
        v["slepc4py"] = slepc4py.__version__
    except ImportError:
        pass
    return "; ".join(f"{k}={x}" for k, x in v.items())


def state_groups(state: State) -> dict:
    arrays = dict(s=state.s, h0=state.h0, E=state.E)
    if state.bonds is not None:
        bd = state.bonds
        arrays["bonds"] = dict(i=bd.i, j=bd.j, shift=bd.shift, l0=bd.l0)
    if state.radii is not None:
        arrays["radii"] = state.radii
    return arrays


class Leg:
    """Stop rules of one leg of the protocol, and its progress for the ETA."""

    def __init__(self, spec: dict, index: int, n_legs: int):
        self.spec, self.index, self.n_legs = spec, index, n_legs
        self.direction = +1 if spec["direction"] == "forward" else -1

    def reason_to_stop(self, obs: dict, leg_strain: float, leg_steps: int) -> str | None:
        sp = self.spec
        for q in ("sigma", "V2"):
            if f"{q}_above" in sp and obs[q] >= sp[f"{q}_above"]:
                return f"{q} = {obs[q]:.4g} >= {sp[f'{q}_above']:g}"
            if f"{q}_below" in sp and obs[q] <= sp[f"{q}_below"]:
                return f"{q} = {obs[q]:.4g} <= {sp[f'{q}_below']:g}"
        if "strain" in sp and leg_strain >= sp["strain"] * (1 - 1e-12):
            return f"leg strain {leg_strain:.6g} reached"
        if "max_steps" in sp and leg_steps >= sp["max_steps"]:
            return f"leg step budget {sp['max_steps']} used"
        return None

    def fraction(self, obs: dict, start: dict, leg_strain: float, leg_steps: int) -> float:
        sp, f = self.spec, 0.0
        for q in ("sigma", "V2"):
            x, x0 = obs[q], start[q]
            if x > 0 and x0 > 0:
                if f"{q}_above" in sp and sp[f"{q}_above"] > x0:
                    f = max(f, math.log(x / x0) / math.log(sp[f"{q}_above"] / x0))
                if f"{q}_below" in sp and sp[f"{q}_below"] < x0:
                    f = max(f, math.log(x0 / x) / math.log(x0 / sp[f"{q}_below"]))
        if "strain" in sp:
            f = max(f, leg_strain / sp["strain"])
        if "max_steps" in sp:
            f = max(f, leg_steps / sp["max_steps"])
        return min(max(f, 0.0), 1.0)


class Run:
    def __init__(self, scene: dict, comm, path: str, quiet: bool = False,
                 cmdline_options: set[str] | None = None, restart: bool = False,
                 max_steps: int | None = None):
        self.scene, self.comm, self.path = scene, comm, path
        self.rank = comm.getRank()
        self.quiet = quiet
        self.restart = restart
        if max_steps is not None:
            scene["protocol"]["max_steps"] = max_steps
        self.model = get_model(scene["model"]["name"])
        StepControl(**scene["integrator"]).validate()
        self.obs_cfg = scene["observables"]
        self.cmdline = cmdline_options or set()

    # ------------------------------------------------------------------------------------
    def _build_state(self) -> State:
        # built on rank 0 and broadcast; an InputError there is raised on every rank
        return collective(self.comm, self.model.build, self.scene["model"], self.scene["seed"])

    # ------------------------------------------------------------------------------------
    def execute(self) -> str:
        comm, scene = self.comm, self.scene
        t_start = time.monotonic()
        writer = RunWriter(self.path, scene["output"]["flush_seconds"]) if self.rank == 0 else None
        if self.restart:
            state, ck = self._load_checkpoint()
        else:
            state, ck = self._build_state(), None
        eng = make_engine(comm, state, scene, self.model, ck)
        state = eng.state
        legs = [Leg(x, k, len(scene["protocol"]["leg"])) for k, x in enumerate(scene["protocol"]["leg"])]

        if ck is None:
            step, strain = 0, 0.0
            leg_k, leg_strain, leg_steps, level, strain_mark = 0, 0.0, 0, None, 0
        else:
            step, strain = ck["step"], ck["strain"]
            leg_k, leg_strain, leg_steps = ck["leg"], ck["leg_strain"], ck["leg_steps"]
            level = None if ck["level"] == -10**9 else ck["level"]
            strain_mark = int(ck.get("strain_mark", 0))

        eng.start()
        solver_desc, opts = eng.describe()
        opts.update(PETSc.Options().getAll())
        unused = [o for o in unused_options() if not o.startswith(("spec_", "options_left"))]
        if unused:
            log.warning("WARNING: PETSc options set but not used: %s", ", ".join("-" + u for u in unused))

        def start_file(writer):
            if ck is None:
                attrs = dict(parflow_version=__version__, scene=scene["text"],
                             petsc_options="\n".join(f"-{k} {v}" for k, v in sorted(opts.items())),
                             solver=solver_desc, parallel=eng.parallel, versions=versions(), n_ranks=comm.getSize(),
                             git_commit=git_commit(), created=time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                             status="running", message="", model=scene["model"]["name"],
                             engine=eng.kind, scene_settings="\n".join(scene.get("settings", [])))
                writer.create(attrs, {"initial": (state_groups(state), {}),
                                      "model": ({}, {k: v for k, v in state.meta.items()
                                                     if isinstance(v, (int, float, str))})})
            else:
                writer.reopen(ck["n_rows"], ck["step"])
                writer.set_attrs(status="running", restarted_at_step=step,
                                 restarted=time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                                 restart_git_commit=git_commit(),
                                 scene_settings="\n".join(scene.get("settings", [])))
        # rank 0 writes; a failure there (full disk) is one WriteError on every rank
        collective_write(comm, writer, start_file)
        log.info("%s: %s, %s, %d rank(s) (%s), solver %s%s", scene["model"]["name"],
                 scene["title"] or "untitled", eng.size_text(), comm.getSize(),
                 eng.parallel, solver_desc, f", restarting at step {step}" if ck else "")

        status, message = "running", ""
        rows_written = ck["n_rows"] if ck else 0
        self._engine = eng
        last_ck_step, last_ck_time = step, time.monotonic()
        last_progress = 0.0
        eta_est = EtaEstimate()
        wom_last = float("nan")
        t_leg = time.monotonic()
        steps_at_leg_start = step

        def record(obs, wom):
            nonlocal rows_written
            row = dict(step=step, gamma=eng.gamma, strain=strain, leg=leg_k,
                       direction=legs[min(leg_k, len(legs) - 1)].direction,
                       omega_min=wom, wall=time.monotonic() - t_start)
            row.update(eng.row())
            row.update(obs)
            if writer:
                writer.append(row)
            rows_written += 1

        def checkpoint():
            if writer:
                arrays, attrs = eng.checkpoint()
                attrs.update(step=step, strain=strain, leg=leg_k, leg_strain=leg_strain,
                             leg_steps=leg_steps, n_rows=rows_written, strain_mark=strain_mark,
                             level=-10**9 if level is None else level)
                writer.set_checkpoint(arrays, attrs)

        def failed(exc):
            """The run stops on ``exc``: rank 0 writes the status, the reason, a checkpoint
            at the last whole step (not after a second signal, nor when the file could not
            be written: then only the status, if it fits) and removes the shadow file."""
            nonlocal status, message
            stopped = isinstance(exc, (KeyboardInterrupt, Terminated))
            status = "interrupted" if stopped else "failed"
            message = (f"{type(exc).__name__}: {exc} (step {step}, gamma = {eng.gamma:.10g}, "
                       f"sigma = {obs['sigma']:.4g})"
                       + ("; continue with --restart" if stopped else ""))
            mid_step = getattr(exc, "mid_step", False)
            if mid_step:
                message += " (second signal: stopped mid-step, no new checkpoint)"
            if writer:
                full = isinstance(exc, WriteError)   # the data did not fit: the status may
                if not (full or mid_step):
                    checkpoint()
                lost = writer.close(data=not full, status=status, message=message, steps=step,
                                    wall_seconds=time.monotonic() - t_start,
                                    loadavg_end=np.array(os.getloadavg()), **eng.counters())
                if lost and not full:        # (full: the WriteError's line says it)
                    log.warning("WARNING: %s", lost)

        obs = eng.observe()
        leg_start_obs = dict(obs)
        if ck is None:
            wom = eng.omega_min() if self.obs_cfg["omega_min_every"] else float("nan")
            record(obs, wom)
            self._analysis(writer, eng, step, strain, obs)
        with STOPS.deferred():   # a signal stops the loop between steps
            try:
                while leg_k < len(legs):
                    STOPS.check(comm)
                    leg = legs[leg_k]
                    why = leg.reason_to_stop(obs, leg_strain, leg_steps)
                    if why is None and step >= scene["protocol"]["max_steps"]:
                        status, message = "budget", f"step budget protocol.max_steps = {step} used"
                        log.info("stopping: %s", message)
                        break
                    if why is not None:
                        log.info("leg %d/%d (%s) done at step %d, gamma = %.10g: %s", leg_k + 1,
                                 len(legs), leg.spec["direction"], step, eng.gamma, why)
                        self._analysis(writer, eng, step, strain, obs)
                        leg_k, leg_strain, leg_steps = leg_k + 1, 0.0, 0
                        leg_start_obs, t_leg, steps_at_leg_start = dict(obs), time.monotonic(), step
                        eta_est = EtaEstimate()
                        continue
                    cap = leg.spec["strain"] - leg_strain if "strain" in leg.spec else None
                    dgamma = eng.step(leg.direction, cap)
                    step += 1
                    leg_steps += 1
                    strain += abs(dgamma)
                    leg_strain += abs(dgamma)
                    obs = eng.observe()
                    every = self.obs_cfg["omega_min_every"]
                    wom = eng.omega_min() if every and step % every == 0 else float("nan")
                    wom_last = wom if np.isfinite(wom) else wom_last
                    record(obs, wom)
                    if not (np.isfinite(obs["sigma"]) and np.isfinite(obs["V2"])):
                        raise SolveError(f"non-finite stress at step {step}, gamma = {eng.gamma:.10g}")
                    level, strain_mark = self._maybe_analysis(writer, eng, step, strain, obs, level,
                                                              strain_mark)
                    snap = self.obs_cfg["snapshot_every"]
                    if writer and snap and step % snap == 0:
                        writer.add_group(f"snapshots/{step:08d}", eng.snapshot(),
                                         dict(step=step, gamma=eng.gamma, sigma=obs["sigma"]))
                    now = time.monotonic()
                    take = step - last_ck_step >= scene["output"]["checkpoint_every"] or \
                        now - last_ck_time >= 60 * scene["output"]["checkpoint_minutes"]
                    if take:
                        checkpoint()
                        last_ck_step, last_ck_time = step, now
                    # a checkpoint is on disk when it is taken: flushed with it (a flush costs
                    # what it appends, docs/output.md "Faults"); on several ranks, one
                    # broadcast per step carries a write failure on rank 0 to every rank
                    collective_write(comm, writer, lambda w: w.flush() if take or w.due() else None)
                    if now - last_progress >= scene["output"]["progress_seconds"]:
                        last_progress = now
                        frac = leg.fraction(obs, leg_start_obs, leg_strain, leg_steps)
                        rate = (step - steps_at_leg_start) / max(now - t_leg, 1e-9)
                        eta = eta_est.update(now, frac, step)
                        log.info("step %7d  leg %d/%d %s  gamma=%+.9e  sigma=%.3e  V2=%.3e  dgamma=%.2e%s"
                                 "  %.1f steps/s  leg ETA %s", step, leg_k + 1, len(legs),
                                 "fwd" if leg.direction > 0 else "rev", eng.gamma, obs["sigma"], obs["V2"],
                                 abs(dgamma), f"  omega_min={wom_last:.3e}" if np.isfinite(wom_last) else "",
                                 rate, _hms(eta))
                else:
                    status, message = "complete", f"all {len(legs)} legs done"
            except Jammed as exc:
                status, message = "jammed", str(exc)
                log.info("stopping: %s", message)
                eng.on_jammed()
                self._analysis(writer, eng, step, strain, obs)
            except BaseException as exc:
                failed(exc)
                raise
            try:              # the last write, still deferring signals
                checkpoint()
                if writer:
                    writer.set_attrs(status=status, message=message, steps=step,
                                     wall_seconds=time.monotonic() - t_start,
                                     loadavg_end=np.array(os.getloadavg()), **eng.counters())
                collective_write(comm, writer, lambda w: w.flush(final=True))
            except BaseException as exc:
                failed(exc)
                raise
        log.info("%s: %s; %d steps, %.1f s; wrote %s", status, message, step,
                 time.monotonic() - t_start, self.path)
        eng.destroy()
        return status

    # ------------------------------------------------------------------------------------
    def _maybe_analysis(self, writer, eng, step, strain, obs, level, strain_mark):
        """Analyses every ``analysis_every`` steps, every ``analysis_strain`` of accumulated
        strain, or ``analysis_per_decade`` times per decade of the analysis quantity; none
        before ``analysis_from_strain``.  Returns the updated (level, strain_mark)."""
        cfg = self.obs_cfg
        if strain < cfg["analysis_from_strain"]:
            return level, strain_mark
        if cfg["analysis_every"] and step % cfg["analysis_every"] == 0:
            self._analysis(writer, eng, step, strain, obs)
            return level, strain_mark
        if cfg["analysis_strain"] > 0:
            mark = int(math.floor((strain - cfg["analysis_from_strain"]) / cfg["analysis_strain"]))
            if mark > strain_mark:
                self._analysis(writer, eng, step, strain, obs)
                return level, mark
        if cfg["analysis_per_decade"] > 0:
            q = obs[cfg["analysis_quantity"]]
            if q > 0:
                new = int(math.floor(cfg["analysis_per_decade"] * math.log10(q)))
                if level is not None and new != level:
                    self._analysis(writer, eng, step, strain, obs)
                return new, strain_mark
        return level, strain_mark

    def _analysis(self, writer, eng, step, strain, obs):
        cfg = self.obs_cfg
        if not (cfg["analysis_every"] or cfg["analysis_per_decade"] or cfg["analysis_strain"]):
            return
        if strain < cfg["analysis_from_strain"]:
            return
        out = eng.analyses()
        if writer:
            attrs = dict(step=step, gamma=eng.gamma, strain=strain, **{k: v for k, v in obs.items()})
            attrs.update(out["scalars"])
            writer.add_group(f"analysis/{step:08d}", out["arrays"], attrs)

    def _load_checkpoint(self):
        """The initial state and the checkpoint of the file being restarted, read and checked
        (``check_checkpoint``) on rank 0 before anything touches the file; a bad checkpoint
        is one InputError on every rank."""
        init, ck, meta = collective(self.comm, _read_checkpoint, self.path,
                                    len(self.scene["protocol"]["leg"]), self.scene["model"]["name"])
        bonds = None
        if "bonds" in init:
            bd = init["bonds"]
            bonds = Bonds(bd["i"], bd["j"], bd["shift"], bd["l0"])
        state = State(init["s"], init["h0"], init["E"], 0.0, bonds, init.get("radii"), meta=meta)
        ck = {k: (v.item() if hasattr(v, "item") and np.ndim(v) == 0 else v) for k, v in ck.items()}
        return state, ck


def _read_checkpoint(path: str, n_legs: int, model: str):
    f = read_run(path)
    try:
        check_checkpoint(f, path, n_legs, model)
        init = load_group(f["initial"])
        ck = dict(f["checkpoint"].attrs)
        ck.update(load_group(f["checkpoint"]))
        meta = dict(f["model"].attrs) if "model" in f else {}
    finally:
        f.close()
    return init, ck, meta


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
    import h5py

    def bad(what: str):
        raise InputError(f"{path!r}: cannot restart from its checkpoint: {what}; the file was not changed")

    if not isinstance(f.get("checkpoint"), h5py.Group):
        raise InputError(f"{path!r} has no checkpoint: it cannot be restarted; the file was not changed")
    for g in ("initial", "timeseries"):
        if not isinstance(f.get(g), h5py.Group):
            bad(f"the file has no /{g} group")
    name = _text(f.attrs.get("model", ""))
    from .models import MODELS
    if name not in MODELS:
        bad(f"the file's model attribute is {name!r}, not one of {list(MODELS)}")
    if model is not None and model != name:
        bad(f"the file's model is {name!r} but its scene's is {model!r}")
    kind = getattr(get_model(name), "ENGINE", "bonded")
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
    import h5py

    from .geometry import cell_at, pair_vectors
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


class EtaEstimate:
    """Leg ETA from the recent rate of progress (the fraction of the leg done, measured in
    log sigma or log V2 for stress targets): approaching jamming, progress slows down, so the
    rate over the last ~30 s is a better guide than the average since the leg began.  The
    window also spans at least ``min_steps`` steps: with steps of 10 s or more (N = 10^6) a
    30 s window sees a few steps, and sigma's own ups and downs swamp the trend."""

    def __init__(self, window: float = 30.0, min_steps: int = 30):
        self.window, self.min_steps = window, min_steps
        self.hist: list[tuple[float, float, int]] = []

    def update(self, now: float, frac: float, step: int = 0) -> float:
        self.hist.append((now, frac, step))
        while len(self.hist) > 2 and now - self.hist[1][0] > self.window \
                and step - self.hist[1][2] >= self.min_steps:
            self.hist.pop(0)
        t0, f0, _ = self.hist[0]
        if now <= t0 or frac <= f0:
            return float("nan")
        return (1.0 - frac) * (now - t0) / (frac - f0)


def _hms(t: float) -> str:
    if not np.isfinite(t):
        return "--:--:--"
    t = int(t)
    return f"{t // 3600}:{t % 3600 // 60:02d}:{t % 60:02d}"

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
from .engines import _at, make_engine  # noqa: F401  (_at: used by tests and analyses)
from .integrate import Jammed, StepControl
from .io import RunWriter, load_group, read_run
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
        if self.rank == 0:
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
                    if step - last_ck_step >= scene["output"]["checkpoint_every"] or \
                            now - last_ck_time >= 60 * scene["output"]["checkpoint_minutes"]:
                        checkpoint()
                        last_ck_step, last_ck_time = step, now
                    if writer and writer.due():
                        writer.flush()
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
                stopped = isinstance(exc, (KeyboardInterrupt, Terminated))
                status = "interrupted" if stopped else "failed"
                message = (f"{type(exc).__name__}: {exc} (step {step}, gamma = {eng.gamma:.10g}, "
                           f"sigma = {obs['sigma']:.4g})"
                           + ("; continue with --restart" if stopped else ""))
                if getattr(exc, "mid_step", False):
                    message += " (second signal: stopped mid-step, no new checkpoint)"
                if writer:
                    if not getattr(exc, "mid_step", False):
                        checkpoint()
                    writer.set_attrs(status=status, message=message, steps=step,
                                     wall_seconds=time.monotonic() - t_start,
                                     loadavg_end=np.array(os.getloadavg()), **eng.counters())
                    writer.flush()
                raise
        checkpoint()
        if writer:
            writer.set_attrs(status=status, message=message, steps=step,
                             wall_seconds=time.monotonic() - t_start,
                             loadavg_end=np.array(os.getloadavg()), **eng.counters())
            writer.flush()
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
        f = None
        if self.rank == 0:
            f = read_run(self.path)
        ok = self.comm.tompi4py().bcast(f is not None and "checkpoint" in f, root=0)
        if not ok:
            raise InputError(f"{self.path!r} has no checkpoint to restart from")
        data = None
        if self.rank == 0:
            init = load_group(f["initial"])
            ck = dict(f["checkpoint"].attrs)
            ck.update(load_group(f["checkpoint"]))
            meta = dict(f["model"].attrs) if "model" in f else {}
            f.close()
            data = (init, ck, meta)
        init, ck, meta = self.comm.tompi4py().bcast(data, root=0)
        bonds = None
        if "bonds" in init:
            bd = init["bonds"]
            bonds = Bonds(bd["i"], bd["j"], bd["shift"], bd["l0"])
        state = State(init["s"], init["h0"], init["E"], 0.0, bonds, init.get("radii"), meta=meta)
        ck = {k: (v.item() if hasattr(v, "item") and np.ndim(v) == 0 else v) for k, v in ck.items()}
        return state, ck


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

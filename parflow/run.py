"""The step loop: scene -> model -> State -> legs of adaptive steps -> HDF5 (DESIGN §3).

A run is one engine (``dynamics.engines``: it owns the evolving State and knows what a strain
step is) and the schedule of what happens after each accepted step, as data: a list of
``(trigger, action)`` pairs (``protocol``), each trigger keeping its own memory, which goes
into the checkpoint so that a restart resumes every schedule where it was.  After a step, in
this order: omega_min (every ``omega_min_every`` steps) -> the time-series row -> analyses
(every n steps / every strain interval / k per decade, none before a strain) -> snapshot ->
checkpoint (n steps or m minutes) -> flush (with each checkpoint, else every s seconds) ->
progress line (every s seconds).

Every rank runs the same loop on replicated geometry; PETSc distributes the algebra; rank 0
alone writes the file and prints.
"""
from __future__ import annotations

import logging
import os
import sys
import time

import numpy as np

from . import __version__
from .checkpoint import read_checkpoint
from .errors import collective
from .dynamics.engines import make_engine
from .dynamics.heun import Jammed
from .io import RunWriter, WriteError, collective_write
from .models import get_model
from .protocol import (Clock, Elapsed, Every, Leg, WallEvery, analyses_enabled,
                       analysis_trigger, hms, pace)
from .provenance import git_commit, versions
from .algebra.solvers import SolveError, all_options, unused_options
from .state import STOPS, State, Terminated

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


class Run:
    def __init__(self, scene: dict, comm, path: str, quiet: bool = False,
                 cmdline_options: set[str] | None = None, restart: bool = False,
                 max_steps: int | None = None, file_attrs: dict | None = None):
        self.scene, self.comm, self.path = scene, comm, path
        self.file_attrs = dict(file_attrs or {})   # more root attributes of a new file (an
        # ensemble's sample index and seed, parflow.ensemble)
        self.rank = comm.getRank()
        self.quiet = quiet
        self.restart = restart
        if max_steps is not None:
            scene["protocol"]["max_steps"] = max_steps
        self.model = get_model(scene["model"]["name"])
        self.obs_cfg = scene["observables"]
        self.cmdline = cmdline_options or set()

    # ------------------------------------------------------------------------------------
    def _build_state(self) -> State:
        # built on rank 0 and broadcast; an InputError there is raised on every rank
        return collective(self.comm, self.model.build, self.scene["model"], self.scene["seed"])

    def load_checkpoint(self):
        """The initial state and the checkpoint of the file being restarted, read and checked
        (``checkpoint.check_checkpoint``) on rank 0 before anything touches the file; a bad
        checkpoint is one InputError on every rank."""
        init, ck, meta = collective(self.comm, read_checkpoint, self.path,
                                    len(self.scene["protocol"]["leg"]), self.scene["model"]["name"])
        state = State.from_groups(init, 0.0, meta)
        ck = {k: (v.item() if hasattr(v, "item") and np.ndim(v) == 0 else v) for k, v in ck.items()}
        return state, ck

    # ------------------------------------------------------------------------------------
    def execute(self) -> str:
        comm, scene, cfg, out = self.comm, self.scene, self.obs_cfg, self.scene["output"]
        t_start = time.monotonic()
        writer = RunWriter(self.path, out["flush_seconds"]) if self.rank == 0 else None
        state, ck = self.load_checkpoint() if self.restart else (self._build_state(), None)
        eng = make_engine(comm, state, scene, self.model, ck)
        self._engine = eng
        state = eng.state
        legs = [Leg(x, k, len(scene["protocol"]["leg"])) for k, x in enumerate(scene["protocol"]["leg"])]
        clock = Clock() if ck is None else Clock.restore(ck)

        def begin_leg(ck=None) -> bool:
            """The current leg's own keys (bonded models): its integrator settings, and -- when
            the leg really begins, not on a restart inside it (``ck``) -- its perturb.  True if
            the nodes were displaced."""
            if clock.leg >= len(legs):
                return False
            spec = legs[clock.leg].spec
            if eng.use_integrator(spec.get("integrator"), ck) and ck is None:
                log.info("leg %d/%d: integrator %s", clock.leg + 1, len(legs),
                         ", ".join(f"{k} = {v}" for k, v in spec.get("integrator", {}).items())
                         or "as [integrator]")
            rms = spec.get("perturb", 0.0) if ck is None else 0.0
            if rms > 0:
                moved = eng.perturb(rms, spec.get("perturb_seed", scene["seed"]), clock.leg)
                log.info("leg %d/%d: nodes displaced by %.3g a0 rms (perturb = %g), rod lengths "
                         "restored", clock.leg + 1, len(legs), moved, rms)
            return rms > 0

        # the schedule (protocol triggers); their memory is restored from the checkpoint
        omega_due = Every(cfg["omega_min_every"])
        analysis_due = analysis_trigger(cfg)
        snapshot_due = Every(cfg["snapshot_every"])
        progress_due = WallEvery(out["progress_seconds"])
        if ck is not None:
            analysis_due.restore(ck)

        eng.start()
        solver_desc, opts = eng.describe()
        opts.update(all_options())
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
                             engine=eng.kind, scene_settings="\n".join(scene.get("settings", [])),
                             **self.file_attrs)
                writer.create(attrs, {"initial": (state.to_groups(), {}),
                                      "model": ({}, {k: v for k, v in state.meta.items()
                                                     if isinstance(v, (int, float, str))})})
            else:
                writer.reopen(ck["n_rows"], ck["step"])
                writer.set_attrs(status="running", restarted_at_step=clock.step,
                                 restarted=time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                                 restart_git_commit=git_commit(),
                                 scene_settings="\n".join(scene.get("settings", [])),
                                 **self.file_attrs)
        # rank 0 writes; a failure there (full disk) is one WriteError on every rank
        collective_write(comm, writer, start_file)
        log.info("%s: %s, %s, %d rank(s) (%s), solver %s%s", scene["model"]["name"],
                 scene["title"] or "untitled", eng.size_text(), comm.getSize(),
                 eng.parallel, solver_desc, f", restarting at step {clock.step}" if ck else "")

        status, message = "running", ""
        rows = [ck["n_rows"] if ck else 0]          # rows written (the checkpoint's n_rows)
        row_step = [ck["step"] if ck else None]     # the step of the last row written
        checkpoint_due = Elapsed(steps=out["checkpoint_every"], seconds=60 * out["checkpoint_minutes"],
                                 start_step=clock.step)
        def current_leg():
            """The leg being run (the last one once all are done)."""
            return legs[min(clock.leg, len(legs) - 1)]

        eta = current_leg().eta()
        wom_last = float("nan")
        leg_t0, leg_step0 = time.monotonic(), clock.step

        def record(obs, wom):
            row = dict(step=clock.step, gamma=eng.gamma, strain=clock.strain, leg=clock.leg,
                       direction=current_leg().direction,
                       omega_min=wom, wall=time.monotonic() - t_start)
            row.update(eng.row())
            row.update(obs)
            if writer:
                writer.append(row)
            rows[0] += 1
            row_step[0] = clock.step

        def analyse(obs):
            """The model's analyses at this instant, into /analysis/<step>."""
            if not analyses_enabled(cfg) or clock.strain < cfg["analysis_from_strain"]:
                return
            res = eng.analyses()
            if writer:
                attrs = dict(step=clock.step, gamma=eng.gamma, strain=clock.strain, **obs)
                attrs.update(res["scalars"])
                writer.add_group(f"analysis/{clock.step:08d}", res["arrays"], attrs)

        def snapshot(obs):
            if writer:
                writer.add_group(f"snapshots/{clock.step:08d}", eng.snapshot(),
                                 dict(step=clock.step, gamma=eng.gamma, sigma=obs["sigma"]))

        def checkpoint():
            if writer:
                arrays, attrs = eng.checkpoint()
                attrs.update(clock.state(), n_rows=rows[0], strain_mark=0, level=-10**9)
                attrs.update(analysis_due.state())        # the schedule's memory
                writer.set_checkpoint(arrays, attrs)

        def progress(obs, dgamma, leg, leg_obs0):
            now = time.monotonic()
            frac = leg.fraction(obs, leg_obs0, clock.leg_strain, clock.leg_steps)
            rate = (clock.step - leg_step0) / max(now - leg_t0, 1e-9)
            log.info("step %7d  leg %d/%d %s  gamma=%+.9e  sigma=%.3e  V2=%.3e  dgamma=%.2e%s%s"
                     "  %s  leg ETA %s", clock.step, clock.leg + 1, len(legs),
                     "fwd" if leg.direction > 0 else "rev", eng.gamma, obs["sigma"], obs["V2"],
                     abs(dgamma), f"  phi={obs['phi']:.5f}" if "phi" in obs else "",
                     f"  omega_min={wom_last:.3e}" if np.isfinite(wom_last) else "",
                     pace(rate), hms(eta.update(now, frac, clock.step)))

        def failed(exc):
            """The run stops on ``exc``: rank 0 writes the status, the reason, a checkpoint
            at the last whole step (not after a second signal, nor when the file could not
            be written: then only the status, if it fits; nor when ``exc`` came between a
            step and its row -- the file's earlier checkpoint then stays the one to restart
            from) and removes the shadow file."""
            nonlocal status, message
            stopped = isinstance(exc, (KeyboardInterrupt, Terminated))
            status = "interrupted" if stopped else "failed"
            message = (f"{type(exc).__name__}: {exc} (step {clock.step}, gamma = {eng.gamma:.10g}, "
                       f"sigma = {obs['sigma']:.4g})"
                       + ("; continue with --restart" if stopped else ""))
            mid_step = getattr(exc, "mid_step", False)
            if mid_step:
                message += " (second signal: stopped mid-step, no new checkpoint)"
            if writer:
                full = isinstance(exc, WriteError)   # the data did not fit: the status may
                if not (full or mid_step) and row_step[0] == clock.step:
                    checkpoint()
                lost = writer.close(data=not full, status=status, message=message, steps=clock.step,
                                    wall_seconds=time.monotonic() - t_start,
                                    loadavg_end=np.array(os.getloadavg()), **eng.counters())
                if lost and not full:        # (full: the WriteError's line says it)
                    log.warning("WARNING: %s", lost)

        begin_leg(ck)
        obs = eng.observe()
        leg_obs0 = dict(obs)
        if ck is None:
            record(obs, eng.omega_min() if omega_due.fires(clock, obs, 0.0) else float("nan"))
            analyse(obs)
        with STOPS.deferred():   # a signal stops the loop between steps
            try:
                while clock.leg < len(legs):
                    STOPS.check(comm)
                    leg = legs[clock.leg]
                    why = leg.reason_to_stop(obs, clock.leg_strain, clock.leg_steps)
                    if why is None and clock.step >= scene["protocol"]["max_steps"]:
                        status, message = "budget", f"step budget protocol.max_steps = {clock.step} used"
                        log.info("stopping: %s", message)
                        break
                    if why is not None:
                        log.info("leg %d/%d (%s) done at step %d, gamma = %.10g: %s", clock.leg + 1,
                                 len(legs), leg.spec["direction"], clock.step, eng.gamma, why)
                        analyse(obs)
                        clock.next_leg()
                        if begin_leg():
                            obs = eng.observe()
                        leg_obs0, leg_t0, leg_step0, eta = dict(obs), time.monotonic(), clock.step, current_leg().eta()
                        continue
                    cap = leg.spec["strain"] - clock.leg_strain if "strain" in leg.spec else None
                    dgamma = eng.step(leg.direction, cap)
                    clock.advance(dgamma)
                    obs = eng.observe()
                    wom = eng.omega_min() if omega_due.fires(clock, obs, 0.0) else float("nan")
                    wom_last = wom if np.isfinite(wom) else wom_last
                    record(obs, wom)
                    if not (np.isfinite(obs["sigma"]) and np.isfinite(obs["V2"])):
                        raise SolveError(f"non-finite stress at step {clock.step}, gamma = {eng.gamma:.10g}")
                    if analysis_due.fires(clock, obs, time.monotonic()):
                        analyse(obs)
                    if snapshot_due.fires(clock, obs, 0.0):
                        snapshot(obs)
                    take = checkpoint_due.fires(clock, obs, time.monotonic())
                    if take:
                        checkpoint()
                    # a checkpoint is on disk when it is taken: flushed with it (a flush costs
                    # what it appends, docs/output.md "Faults"); on several ranks, one
                    # broadcast per step carries a write failure on rank 0 to every rank
                    collective_write(comm, writer, lambda w: w.flush() if take or w.due() else None)
                    if progress_due.fires(clock, obs, time.monotonic()):
                        progress(obs, dgamma, leg, leg_obs0)
                else:
                    status, message = "complete", f"all {len(legs)} legs done"
            except Jammed as exc:
                status, message = "jammed", str(exc)
                log.info("stopping: %s", message)
                cert = getattr(exc, "certificate", None)
                if writer and cert:      # the proof of jamming (contact LCP): /jam
                    writer.add_group("jam", getattr(exc, "arrays", {}),
                                     dict(cert, step=clock.step))
                eng.on_jammed()
                analyse(obs)
            except BaseException as exc:
                failed(exc)
                raise
            try:              # the last write, still deferring signals
                checkpoint()
                if writer:
                    writer.set_attrs(status=status, message=message, steps=clock.step,
                                     wall_seconds=time.monotonic() - t_start,
                                     loadavg_end=np.array(os.getloadavg()), **eng.counters())
                collective_write(comm, writer, lambda w: w.flush(final=True))
            except BaseException as exc:
                failed(exc)
                raise
        log.info("%s: %s; %d steps, %.1f s; wrote %s", status, message, clock.step,
                 time.monotonic() - t_start, self.path)
        eng.destroy()
        return status


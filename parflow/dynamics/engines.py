"""Step engines of the driver (``parflow.run``): what one strain step *is* for a model.

The driver (legs, stop rules, output, checkpoints, progress, analyses schedule) is the same
for every model; an engine owns the physics of a step:

* :class:`BondedEngine` -- persistent rods (chain, network): Heun with error control and
  projection on the rod lengths (``dynamics.heun.Heun``), forces from N tau = -b
  (``dynamics.bonded.BondedSystem``).
* :class:`ContactEngine` -- hard-disc suspension: contacts found anew every step, forces
  from the contact LCP, conservative no-overlap step (``dynamics.hard_discs.Suspension``).

Both expose: ``start()`` (forces at the initial configuration), ``step(direction, cap)``,
``observe()``, ``row()`` (per-step diagnostics), ``omega_min()``, ``analyses()``,
``snapshot()``, ``checkpoint()`` / restart through ``restore``, ``describe()``,
``on_jammed()``, ``destroy()``.  ``s`` and ``gamma`` are the engine's current configuration.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..observables import stress
from ..algebra.solvers import collective_cleanup
from ..algebra.spectrum import lowest_omega, on_force_factor
from ..state import InputError, Instant, State
from .bonded import BondedSystem, resolve_reuse
from .hard_discs import ShearJammed, Suspension
from .heun import INTEGRATORS, Jammed, StepControl
from .ros2 import REJECTION_CAUSES


class BondedEngine:
    """Chain and network: Heun steps of the rigid-rod dynamics."""

    kind = "bonded"

    def __init__(self, comm, state: State, scene: dict, model, ck: dict | None = None):
        self.comm, self.state, self.model, self.scene = comm, state, model, scene
        sol = scene["solver"]
        reuse = resolve_reuse(sol["reuse_factor"], len(state.bonds), sol["preset"],
                              model.FACTOR_REUSE)
        self.system = BondedSystem(comm, state, sol["preset"], sol["parallel"], reuse)
        self.control, self.integ = None, None
        # ros2's rejected trial steps by cause, over the integrators this sitting has replaced
        # (a leg that switches ROS2 -> Heun keeps its count); counted for a scene that names
        # ros2 anywhere (its [integrator] or a leg's), not at all otherwise
        legs = scene["protocol"].get("leg", [])
        uses_ros2 = "ros2" in {scene["integrator"].get("method")} | {
            (leg.get("integrator") or {}).get("method") for leg in legs}
        self._rejections = dict.fromkeys(REJECTION_CAUSES, 0) if uses_ros2 else {}
        self.use_integrator(None, ck)
        self.n_eigs = scene["observables"]["n_eigs"]
        self._spec = None
        # the engine owns the evolving state: state.s and state.gamma are always current
        if ck is None:
            state.s, self.dg = state.s.copy(), self.control.initial_dgamma
        else:
            state.s, state.gamma, self.dg = ck["s"], ck["gamma"], ck["dgamma"]
        self.direction = 1          # of the last step (bonded analyses do not depend on it)
        # a checkpoint's rod forces: the restart continues from the very numbers the run had
        # (a force solved with a reused factor differs from a fresh solve by round-off)
        self._tau0 = None if ck is None else ck.get("tau")
        self.F = None
        self.res = None

    @property
    def s(self) -> np.ndarray:
        return self.state.s

    @property
    def gamma(self) -> float:
        return self.state.gamma

    @property
    def parallel(self) -> str:
        return self.system.parallel

    def use_integrator(self, leg_settings: dict | None, ck: dict | None = None) -> bool:
        """Integrate with the scene's [integrator] keys and ``leg_settings`` (a leg's own
        ``integrator`` table) over them.  From a checkpoint ``ck`` the integrator's memory
        (err_prev, its own) is the checkpoint's; otherwise it carries over from the current
        integrator when the method is the same (a new method starts without memory).  Nothing
        changes when the settings are the current ones.  True if the integrator was rebuilt."""
        control = StepControl(**{**self.scene["integrator"], **(leg_settings or {})})
        control.validate()
        if ck is None and control == self.control:
            return False
        old = self.integ
        same = old is not None and control.method == self.control.method
        if ck is not None:
            err_prev = ck.get("err_prev")
            err_prev = float(err_prev) if err_prev is not None and np.isfinite(err_prev) else None
        else:
            err_prev = old.err_prev if same else None
        integ = INTEGRATORS[control.method](self.system, control, err_prev=err_prev)
        if ck is not None:
            integ.recall(ck)
        elif same:
            arrays, attrs = old.memory()
            integ.recall({**arrays, **attrs})
        for k, v in getattr(old, "rejections", {}).items():
            self._rejections[k] = self._rejections.get(k, 0) + int(v)
        self.control, self.integ = control, integ
        return True

    def perturb(self, rms: float, seed: int, leg: int) -> float:
        """Displace every node by a Gaussian vector of ``rms`` a0 per coordinate (the same
        numbers on every rank: seeded by (seed, leg)) and :meth:`displace` there; the rms
        displacement after the projection."""
        rng = np.random.default_rng([int(seed) % 2**63, int(leg), 0x9E3779B9])
        return self.displace(rms * rng.standard_normal(self.s.shape) @ np.linalg.inv(self.F.h).T)

    def displace(self, ds: np.ndarray) -> float:
        """Move the nodes by ``ds`` (fractional coordinates, one row per node), restore the
        rod lengths and solve the force there; the rms displacement (a0) after the
        projection."""
        h = self.F.h
        r0 = self.s @ h.T
        s, _, _ = self.system.project(self.s + ds, self.gamma, tol=self.control.length_tol)
        self.state.s = s
        self.F = self.system.evaluate(s, self.gamma, what="perturbed force")
        d = s @ h.T - r0
        return float(np.sqrt(np.mean(np.einsum("id,id->i", d, d))))

    def start(self):
        tau0, self._tau0 = self._tau0, None
        if tau0 is not None and np.shape(tau0) == (len(self.state.bonds),):
            self.F = self.system.force_from_tau(self.s, self.gamma, tau0)
        else:
            self.F = self.system.evaluate(self.s, self.gamma, what="initial force")
        return self.F

    def describe(self) -> tuple[str, dict]:
        desc = self.system.tau_solver.describe()
        if self.system.reuse_factor:
            desc += ", step's last force by PCG on the predictor's factor"
        return desc, dict(self.system.tau_solver.resolved_options())

    def size_text(self) -> str:
        return f"N = {self.state.n}, Nc = {len(self.state.bonds)}"

    def step(self, direction: int, cap: float | None) -> float:
        res = self.integ.step(self.s, self.gamma, self.F, direction, self.dg, dg_cap=cap)
        self.state.s, self.state.gamma, self.F, self.dg = res.s, res.gamma, res.F, res.next_dgamma
        self.direction = direction
        self.res = res
        return res.dgamma

    def observe(self) -> dict:
        F, state = self.F, self.state
        obs = dict(sigma=F.sigma, sigma_tb=F.sigma_tb, sigma_mismatch=F.sigma_mismatch,
                   pressure=F.pressure,
                   V2=stress.V2(F.V_na),
                   residual=F.info.residual, backward_error=F.info.backward_error,
                   refinements=F.info.refinements)
        obs.update(self.model.observables(state, F))
        return obs

    def row(self) -> dict:
        res = self.res
        if res is None:
            return dict(dgamma=0.0, err=0.0, rejected=0, proj_iter=0,
                        length_error=float(np.max(np.abs(self.F.ell - self.state.bonds.l0))))
        return dict(dgamma=res.dgamma, err=res.err, rejected=res.rejected,
                    length_error=res.length_error, proj_iter=res.proj_iter)

    def omega_min(self) -> float:
        self.system.sync()
        if self._spec is None:      # kept: its Krylov-Schur space is reused from call to call
            self._spec = on_force_factor(self.system, self.n_eigs)
        return lowest_omega(self._spec)

    def instant(self) -> Instant:
        """This instant for the model's analyses (N loaded at the current configuration)."""
        self.system.sync()
        return Instant(self.comm, self.state, self.F, self.system, self.scene, self.direction)

    def analyses(self) -> dict:
        return self.model.analyses(self.instant())

    def snapshot(self) -> dict:
        return dict(s=self.s, V_na=self.F.V_na, tau=self.F.tau)

    def checkpoint(self) -> tuple[dict, dict]:
        ep = self.integ.err_prev
        arrays, attrs = self.integ.memory()          # the integrator's own (RKC: its rho)
        return dict(s=self.s, tau=self.F.tau, **arrays), dict(
            gamma=self.gamma, dgamma=self.dg, err_prev=float("nan") if ep is None else ep, **attrs)

    def on_jammed(self) -> None:
        self.system.load(self.F.n)      # the factor loaded last belongs to a rejected trial step

    def counters(self) -> dict:
        sysm = self.system
        now = getattr(self.integ, "rejections", {})
        return dict(n_factorisations=sysm.n_factor, n_reused_factor=sysm.n_reused,
                    n_reuse_failed=sysm.n_reuse_failed, n_stage_pcg=sysm.n_stage_pcg,
                    n_stage_failed=sysm.n_stage_failed, pcg_iterations=sysm.pcg_iterations,
                    n_suspect_solves=getattr(sysm.tau_solver, "n_suspect", 0),
                    n_force_refreshed=sysm.n_refreshed, krylov_iterations=sysm.krylov_iterations,
                    n_identity_refined=sysm.n_identity_refined,
                    n_factor_rebuilt=getattr(sysm.tau_solver, "n_rebuilt", 0),
                    # ros2's trial steps rejected, by cause, this sitting (0 when it ran no ros2
                    # step: a value from an earlier sitting is not left standing beside them)
                    **{f"rejected_{k}": n + int(now.get(k, 0)) for k, n in self._rejections.items()})

    def destroy(self) -> None:
        if self._spec is not None:
            self._spec.destroy()
        self.system.destroy()


@dataclasses.dataclass
class ContactForce:
    """The contact forces of the suspension at one configuration (what analyses see)."""

    gamma: float
    h: np.ndarray
    c: object            # contacts.Candidates
    f: np.ndarray        # contact forces (>= 0, compressive)
    V_na: np.ndarray     # (N, d)
    sigma: float
    omega: float         # the cell's volume Omega
    direction: int       # the flow direction these forces are for (+1 / -1)
    # -<f|h>/dg / Omega of the step these forces are for, so that sigma = sigma_fb + gap_work
    # (complementarity of the LCP with q = b + h/dg, DESIGN §5): at the first row, before any
    # step, it is that of the step probe() solved for (the first step's), not zero
    gap_work: float = 0.0


class ContactEngine:
    """Hard-disc suspension: one LCP step per strain step (``dynamics.hard_discs``)."""

    kind = "contacts"

    def __init__(self, comm, state: State, scene: dict, model, ck: dict | None = None):
        self.comm, self.state, self.model, self.scene = comm, state, model, scene
        controls = {k: scene["model"][k] for k in Suspension.CONTROLS}
        if ck is None:
            self.sim = Suspension(state, **controls)
        else:
            self.sim = Suspension.restore(dict(
                s=ck["s"], h0=state.h0, gamma=ck["gamma"], radii=state.radii, sigma=ck["sigma"],
                vmax=ck["vmax"], last_dg=ck.get("dgamma", 0.0), active_keys=ck["active_keys"],
                steps=ck["steps"], collisions=ck["collisions"], max_overlap=ck["max_overlap"],
                singular_events=ck["singular_events"],
                infeasible_reductions=ck["infeasible_reductions"], controls=controls,
                **({"phi": ck["phi"]} if "phi" in ck else {})))
            self.state = self.sim.state
            self.state.meta.update(state.meta)
        self.stats = None
        self.F = None
        self._direction = 1 if ck is None else int(ck.get("direction", 1))

    # configuration -----------------------------------------------------------------
    @property
    def s(self) -> np.ndarray:
        return self.sim.state.s

    @property
    def gamma(self) -> float:
        return self.sim.state.gamma

    @property
    def parallel(self) -> str:
        return "replicated"

    def size_text(self) -> str:
        text = f"N = {self.state.n} discs, phi = {self.sim.phi:.4f}"
        if self.sim.compressing:
            text += (f" compressed at {self.sim.compress_rate:g} per unit strain to "
                     f"{self.sim.compress_to:g}")
        return text

    def describe(self) -> tuple[str, dict]:
        return f"contact LCP (active set on {self.sim.factor})", {}

    # forces ------------------------------------------------------------------------
    def perturb(self, rms: float, seed: int, leg: int) -> float:
        raise NotImplementedError("perturb: bonded models only (refused when the scene is loaded)")

    def use_integrator(self, leg_settings: dict | None, ck: dict | None = None) -> bool:
        """No integrator: the contact step's controls are [model] keys (a leg's integrator
        table is refused for this engine when the scene is loaded)."""
        return False

    def probe(self, direction: int | None = None) -> ContactForce:
        """Contact forces at the current configuration for the step the stepper would take
        next, without moving (the first row, and the configuration analyses look at)."""
        sim, st = self.sim, self.sim.state
        direction = self._direction if direction is None else direction
        c, f, V, dg = sim.probe(direction)
        return ContactForce(st.gamma, st.h, c, f, V, stress.sigma(V, sim.omega), sim.omega,
                            direction, stress.gap_work(f, sim.end_gaps(c, dg), dg, sim.omega))

    def start(self):
        self.F = self.probe(+1)
        return self.F

    def step(self, direction: int, cap: float | None) -> float:
        sim = self.sim
        self._direction = direction
        g0 = sim.state.gamma
        try:
            self.stats = sim.step(direction, cap)
        except ShearJammed as exc:
            # the proof travels with it: run.py writes it to the run file's /jam group
            jam = Jammed(str(exc))
            jam.certificate = dict(exc.certificate)
            jam.arrays = (dict(tau=exc.tau, contact_i=exc.pairs[0], contact_j=exc.pairs[1])
                          if exc.tau is not None else {})
            raise jam from None
        st = sim.state
        self.F = ContactForce(st.gamma, st.h, sim.last_c, sim.last_f, sim.last_V, self.stats.sigma,
                              sim.omega, direction, self.stats.gap_work)
        return st.gamma - g0

    def observe(self) -> dict:
        sim, F = self.sim, self.F
        obs = dict(sigma=F.sigma, V2=stress.V2(F.V_na), max_overlap=sim.max_overlap,
                   collisions=sim.collisions)
        if sim.compress_rate > 0:               # a run that compresses: phi per row
            obs["phi"] = sim.phi
        obs.update(self.model.observables(self.state, F))
        return obs

    def row(self) -> dict:
        st = self.stats
        if st is None:
            # the first row, before any step: sigma and sigma_fb are those of the forces
            # probe() solved for the first step, and so is the gap work (sigma = sigma_fb +
            # gap_work holds on this row too); dgamma = 0: no strain has been applied yet
            return dict(dgamma=0.0, n_candidates=len(self.F.c), n_active=int(np.count_nonzero(self.F.f > 0)),
                        n_new=0, n_coll=0, overlap=0.0, lcp_iterations=0, factorizations=0,
                        singular=0, dropped=0, min_w=0.0, gap_work=self.F.gap_work,
                        t_search=0.0, t_lcp=0.0, t_update=0.0)
        return dict(dgamma=self._direction * st.dgamma, n_candidates=st.n_candidates,
                    n_active=st.n_active, n_new=st.n_new, n_coll=st.n_coll, overlap=st.overlap,
                    lcp_iterations=st.lcp.iterations, factorizations=st.lcp.factorizations,
                    singular=st.lcp.singular, dropped=st.lcp.dropped, min_w=st.lcp.min_w,
                    gap_work=st.gap_work,
                    t_search=st.times["search"], t_lcp=st.times["lcp"], t_update=st.times["update"])

    # analyses ----------------------------------------------------------------------
    def _cleanup(self) -> None:
        """Free the PETSc objects of the frozen-network systems now: petsc4py defers the
        destruction of dropped wrappers (each holds a factor) to garbage_cleanup()."""
        collective_cleanup(self.comm, self_too=True)      # collective: every rank is here

    def instant(self) -> Instant:
        """This instant for the model: the forces probed at the current configuration."""
        return Instant(self.comm, self.state, self.probe(), None, self.scene, self._direction)

    def omega_min(self) -> float:
        try:
            return self.model.omega_min(self.instant())
        finally:
            self._cleanup()

    def analyses(self) -> dict:
        try:
            return self.model.analyses(self.instant())
        finally:
            self._cleanup()

    def snapshot(self) -> dict:
        return dict(s=self.s, V_na=self.F.V_na, f=self.F.f, contact_i=self.F.c.i, contact_j=self.F.c.j)

    def checkpoint(self) -> tuple[dict, dict]:
        ck = self.sim.checkpoint()
        arrays = dict(s=ck["s"], active_keys=ck["active_keys"])
        attrs = {k: ck[k] for k in ("gamma", "sigma", "vmax", "steps", "collisions", "max_overlap",
                                    "singular_events", "infeasible_reductions")}
        attrs["direction"] = self._direction
        attrs["dgamma"] = ck["last_dg"]
        if self.sim.compress_rate > 0:
            attrs["phi"] = ck["phi"]
        return arrays, attrs

    def on_jammed(self) -> None:
        pass

    def counters(self) -> dict:
        sim = self.sim
        return dict(collisions=sim.collisions, max_overlap=sim.max_overlap,
                    singular_events=sim.singular_events,
                    infeasible_reductions=sim.infeasible_reductions)

    def destroy(self) -> None:
        pass


def make_engine(comm, state: State, scene: dict, model, ck: dict | None = None):
    if model.ENGINE == "contacts":
        return ContactEngine(comm, state, scene, model, ck)
    if state.bonds is None:
        raise InputError(f"model {scene['model']['name']!r} built a state without bonds")
    return BondedEngine(comm, state, scene, model, ck)

"""The schedule of a run as data: the clock, and triggers that say when an action is due.

A run is one engine stepping the strain plus a list of ``(trigger, action)`` pairs
(:mod:`parflow.run`).  After every accepted step the loop asks each trigger whether its
action is due at the current :class:`Clock`.  A trigger that has memory (the last strain mark,
the last decade, the last wall time) keeps it in itself; what a restart must resume goes into
the checkpoint through :meth:`Trigger.state` / :meth:`Trigger.restore`, so a restarted run
fires exactly where the uninterrupted one would have.

Triggers (small, comparable, printable; ``str()`` names the schedule in logs and files):

* ``Every(n)``              -- step is a multiple of n (n = 0: never)
* ``StrainEvery(x, after)`` -- each time the accumulated strain passes after + k x
* ``PerDecade(q, k)``       -- each time floor(k log10 obs[q]) changes (not the first value)
* ``Elapsed(steps, seconds)`` -- n steps or s seconds since it last fired (both restart then)
* ``WallEvery(s)``          -- s seconds of wall time since it last fired (first call fires)
* ``After(strain, t)``      -- t, asked only once the accumulated strain reaches ``strain``
* ``FirstOf(t1, t2, ...)``  -- the first of its triggers that fires; the later ones are not
  asked then (their memory does not move), as the analysis schedule has always worked
* ``Never()``

Legs (:class:`Leg`) are the protocol's stretches of one flow direction with their stop rules;
:class:`EtaEstimate` turns the progress through a leg into the ETA of the progress line.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from .schema import NON_NEGATIVE, POSITIVE, key

_NO_LEVEL = -10**9      # how run files before the schedule-as-data code stored "no decade yet"


STOP_KEYS = ("sigma_above", "sigma_below", "V2_above", "V2_below", "strain", "max_steps")


@dataclass
class ObservablesOptions:
    """The scene's [observables] table: what is measured when (``schema``)."""
    omega_min_every: int = key(0, *NON_NEGATIVE, "steps between omega_min (0: never)")
    n_eigs: int = key(1, *POSITIVE, "eigenpairs asked of SLEPc for omega_min")
    analysis_quantity: str = key("V2", lambda v: v in ("V2", "sigma"), "'V2' or 'sigma'",
                                 "the quantity analysis_per_decade follows")
    analysis_per_decade: float = key(0.0, *NON_NEGATIVE, "analyses per decade of it (0: none)")
    analysis_every: int = key(0, *NON_NEGATIVE, "or analyses every n steps")
    analysis_strain: float = key(0.0, *NON_NEGATIVE, "or every time this much strain accumulated")
    analysis_from_strain: float = key(0.0, *NON_NEGATIVE, "no analyses before this strain")
    snapshot_every: int = key(0, *NON_NEGATIVE, "steps between snapshots (0: none)")


@dataclass
class ProtocolOptions:
    """The scene's [protocol] table (its legs: [[protocol.leg]], :class:`LegRule`)."""
    max_steps: int = key(1_000_000, *POSITIVE, "total step budget (status 'budget' when used)")
    leg: list = key(None, None, "", "the legs, in order")


@dataclass
class LegRule:
    """One [[protocol.leg]]: a direction and at least one stop rule (the first met ends it)."""
    direction: str = key(None, lambda v: v in ("forward", "reverse"), "'forward' or 'reverse'",
                         "the flow direction")
    sigma_above: float = key(None, *POSITIVE, "stop when sigma >= this")
    sigma_below: float = key(None, *POSITIVE, "stop when sigma <= this")
    V2_above: float = key(None, *POSITIVE, "stop when <V^2> >= this")
    V2_below: float = key(None, *POSITIVE, "stop when <V^2> <= this")
    strain: float = key(None, *POSITIVE, "stop after this much strain in the leg")
    max_steps: int = key(None, *POSITIVE, "stop after this many steps in the leg")
    perturb: float = key(None, *NON_NEGATIVE,
                         "at the start of this leg, displace every node by a Gaussian vector of "
                         "this rms per coordinate (a0; seeded by the scene's seed and the leg's "
                         "index), rod lengths restored (bonded models; 0: nothing)")
    perturb_seed: int = key(None, *NON_NEGATIVE, "the seed of perturb's displacement "
                            "(default: the scene's seed)")
    integrator: dict = key(None, lambda v: len(v) > 0, "a non-empty table of [integrator] keys",
                           "this leg's [integrator] keys, over the scene's (bonded models), "
                           "e.g. integrator = { method = \"heun\" }")


@dataclass
class Clock:
    """Where the run is: accepted steps and strain in all, and within the current leg."""

    step: int = 0
    strain: float = 0.0
    leg: int = 0
    leg_strain: float = 0.0
    leg_steps: int = 0

    def advance(self, dgamma: float) -> None:
        self.step += 1
        self.leg_steps += 1
        self.strain += abs(dgamma)
        self.leg_strain += abs(dgamma)

    def next_leg(self) -> None:
        self.leg, self.leg_strain, self.leg_steps = self.leg + 1, 0.0, 0

    def state(self) -> dict:
        return dict(step=self.step, strain=self.strain, leg=self.leg,
                    leg_strain=self.leg_strain, leg_steps=self.leg_steps)

    @classmethod
    def restore(cls, ck: dict) -> "Clock":
        return cls(int(ck["step"]), float(ck["strain"]), int(ck["leg"]),
                   float(ck["leg_strain"]), int(ck["leg_steps"]))


class Trigger:
    """``fires(clock, obs, now)``: is the action due?  Memory, if any, moves when it fires."""

    def fires(self, clock: Clock, obs: dict, now: float) -> bool:   # pragma: no cover
        raise NotImplementedError

    def state(self) -> dict:
        """What a checkpoint must keep for a restart to resume this schedule exactly."""
        return {}

    def restore(self, ck: dict) -> None:
        pass

    def __eq__(self, other):
        return type(self) is type(other) and vars(self) == vars(other)

    def __repr__(self):
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in vars(self).items())})"


class Never(Trigger):
    def fires(self, clock, obs, now):
        return False


class Every(Trigger):
    def __init__(self, n: int):
        self.n = int(n)

    def fires(self, clock, obs, now):
        return self.n > 0 and clock.step % self.n == 0


class StrainEvery(Trigger):
    """Fires when the accumulated strain enters a new interval [after + k x, after + (k+1) x)
    with k above the last one it fired in (memory ``strain_mark``)."""

    def __init__(self, x: float, after: float = 0.0):
        self.x, self.after, self.mark = float(x), float(after), 0

    def fires(self, clock, obs, now):
        if self.x <= 0:
            return False
        mark = int(math.floor((clock.strain - self.after) / self.x))
        if mark > self.mark:
            self.mark = mark
            return True
        return False

    def state(self):
        return dict(strain_mark=self.mark)

    def restore(self, ck):
        self.mark = int(ck.get("strain_mark", 0))

    def __eq__(self, other):
        return type(other) is StrainEvery and (self.x, self.after) == (other.x, other.after)


class PerDecade(Trigger):
    """Fires ``k`` times per decade of ``obs[quantity]``: when floor(k log10 q) differs from
    the value at the previous call (memory ``level``; the first value only sets it)."""

    def __init__(self, quantity: str, k: float):
        self.quantity, self.k, self.level = quantity, float(k), None

    def fires(self, clock, obs, now):
        if self.k <= 0:
            return False
        q = obs[self.quantity]
        if not q > 0:
            return False
        new = int(math.floor(self.k * math.log10(q)))
        fired = self.level is not None and new != self.level
        self.level = new
        return fired

    def state(self):
        return dict(level=_NO_LEVEL if self.level is None else self.level)

    def restore(self, ck):
        level = ck.get("level", _NO_LEVEL)
        self.level = None if level is None or level == _NO_LEVEL or not math.isfinite(level) \
            else int(level)

    def __eq__(self, other):
        return type(other) is PerDecade and (self.quantity, self.k) == (other.quantity, other.k)


class WallEvery(Trigger):
    """Fires when ``seconds`` of wall time have passed since it last fired (the first call
    fires).  Wall time is not resumed by a restart."""

    def __init__(self, seconds: float):
        self.seconds, self.last = float(seconds), -math.inf

    def fires(self, clock, obs, now):
        if now - self.last >= self.seconds:
            self.last = now
            return True
        return False

    def __eq__(self, other):
        return type(other) is WallEvery and self.seconds == other.seconds


class Elapsed(Trigger):
    """Fires when ``steps`` accepted steps or ``seconds`` of wall time have passed since it
    last fired (or since the run or restart began); both counts restart then."""

    def __init__(self, steps: int | None = None, seconds: float | None = None,
                 start_step: int = 0, start_time: float | None = None):
        self.steps, self.seconds = steps, seconds
        self.last_step = start_step
        self.last_time = time.monotonic() if start_time is None else start_time

    def fires(self, clock, obs, now):
        if (self.steps is not None and clock.step - self.last_step >= self.steps) or \
                (self.seconds is not None and now - self.last_time >= self.seconds):
            self.last_step, self.last_time = clock.step, now
            return True
        return False

    def __eq__(self, other):
        return type(other) is Elapsed and (self.steps, self.seconds) == (other.steps, other.seconds)

    def __repr__(self):
        return f"Elapsed(steps={self.steps!r}, seconds={self.seconds!r})"


class After(Trigger):
    """``inner``, asked only once the accumulated strain has reached ``strain``."""

    def __init__(self, strain: float, inner: Trigger):
        self.strain, self.inner = float(strain), inner

    def fires(self, clock, obs, now):
        return clock.strain >= self.strain and self.inner.fires(clock, obs, now)

    def state(self):
        return self.inner.state()

    def restore(self, ck):
        self.inner.restore(ck)


class FirstOf(Trigger):
    """Fires when one of its triggers fires, asking them in order and stopping at the first
    that does (so the memory of the later ones does not move on that step)."""

    def __init__(self, *triggers: Trigger):
        self.triggers = tuple(t for t in triggers if not isinstance(t, Never))

    def fires(self, clock, obs, now):
        return any(t.fires(clock, obs, now) for t in self.triggers)   # any() stops at the first

    def state(self):
        out = {}
        for t in self.triggers:
            out.update(t.state())
        return out

    def restore(self, ck):
        for t in self.triggers:
            t.restore(ck)

    def __repr__(self):
        return f"FirstOf({', '.join(map(repr, self.triggers))})"


def analysis_trigger(obs_cfg: dict) -> Trigger:
    """The analysis schedule of the scene's [observables] table: every ``analysis_every``
    steps, else every ``analysis_strain`` of accumulated strain, else ``analysis_per_decade``
    times per decade of ``analysis_quantity``; none before ``analysis_from_strain``."""
    c = obs_cfg
    parts = []
    if c["analysis_every"]:
        parts.append(Every(c["analysis_every"]))
    if c["analysis_strain"] > 0:
        parts.append(StrainEvery(c["analysis_strain"], after=c["analysis_from_strain"]))
    if c["analysis_per_decade"] > 0:
        parts.append(PerDecade(c["analysis_quantity"], c["analysis_per_decade"]))
    if not parts:
        return Never()
    return After(c["analysis_from_strain"], FirstOf(*parts))


def analyses_enabled(obs_cfg: dict) -> bool:
    c = obs_cfg
    return bool(c["analysis_every"] or c["analysis_per_decade"] or c["analysis_strain"])


# the window of the ETA of a leg that stops on strain or steps alone (no stress target): its
# progress is linear in strain and its rate only fluctuates -- a flowing suspension at
# phi = 0.840 makes 0.4-2.4 strain per hour in 10-minute windows as sigma swings through its
# excursions, and a 30 s window put "leg ETA" anywhere between 1 and 38 hours
STRAIN_ETA_WINDOW = 600.0


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

    def eta(self) -> "EtaEstimate":
        """The ETA estimator for this leg: over the last 30 s toward a stress target (progress
        slows down as jamming nears), over STRAIN_ETA_WINDOW for a leg that stops on strain
        or steps alone."""
        stress = any(f"{q}_{s}" in self.spec for q in ("sigma", "V2") for s in ("above", "below"))
        return EtaEstimate() if stress else EtaEstimate(window=STRAIN_ETA_WINDOW)

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


def hms(t: float) -> str:
    if not np.isfinite(t):
        return "--:--:--"
    t = int(t)
    return f"{t // 3600}:{t % 3600 // 60:02d}:{t % 60:02d}"


def pace(steps_per_second: float) -> str:
    """The progress line's speed: steps a second, or seconds a step when slower than one a
    second (a large network's steps take seconds: "0.0 steps/s" would say nothing)."""
    r = steps_per_second
    return f"{r:.1f} steps/s" if r >= 1.0 or not r > 0.0 else f"{1.0 / r:.1f} s/step"

"""The schedule as data (parflow.protocol): triggers fire where the hand-written schedule of
the step loop fired, and a restored trigger resumes exactly."""
import math

import numpy as np
import pytest

from parflow.protocol import (After, Clock, Elapsed, Every, FirstOf, Never, PerDecade,
                              StrainEvery, WallEvery, analysis_trigger)


def _old_schedule(cfg, steps):
    """The analysis schedule as the step loop wrote it inline (every n steps, else every
    strain interval, else k per decade; none before from_strain)."""
    level, mark, fired = None, 0, []
    for step, strain, q in steps:
        if strain < cfg["analysis_from_strain"]:
            continue
        if cfg["analysis_every"] and step % cfg["analysis_every"] == 0:
            fired.append(step)
            continue
        if cfg["analysis_strain"] > 0:
            m = int(math.floor((strain - cfg["analysis_from_strain"]) / cfg["analysis_strain"]))
            if m > mark:
                fired.append(step)
                mark = m
                continue
        if cfg["analysis_per_decade"] > 0 and q > 0:
            new = int(math.floor(cfg["analysis_per_decade"] * math.log10(q)))
            if level is not None and new != level:
                fired.append(step)
            level = new
    return fired


def _steps(seed, n=400):
    rng = np.random.default_rng(seed)
    strain = np.cumsum(rng.uniform(0, 2e-3, n))
    q = np.exp(np.cumsum(rng.normal(0.05, 0.3, n)))
    return [(k + 1, float(strain[k]), float(q[k])) for k in range(n)]


CFGS = [dict(analysis_every=0, analysis_strain=0.0, analysis_per_decade=2.0, analysis_from_strain=0.0),
        dict(analysis_every=0, analysis_strain=0.05, analysis_per_decade=0.0, analysis_from_strain=0.1),
        dict(analysis_every=7, analysis_strain=0.03, analysis_per_decade=3.0, analysis_from_strain=0.02),
        dict(analysis_every=0, analysis_strain=0.02, analysis_per_decade=1.5, analysis_from_strain=0.0)]


@pytest.mark.parametrize("cfg", CFGS)
@pytest.mark.parametrize("seed", [1, 2])
def test_analysis_trigger_fires_where_the_inline_schedule_did(cfg, seed):
    cfg = dict(cfg, analysis_quantity="sigma")
    steps = _steps(seed)
    trig = analysis_trigger(cfg)
    got = [st for st, strain, q in steps
           if trig.fires(Clock(step=st, strain=strain), dict(sigma=q), 0.0)]
    assert got == _old_schedule(cfg, steps)
    assert len(got) > 3


@pytest.mark.parametrize("cfg", CFGS)
def test_restored_trigger_resumes_exactly(cfg):
    cfg = dict(cfg, analysis_quantity="sigma")
    steps = _steps(3)
    whole = analysis_trigger(cfg)
    ref = [whole.fires(Clock(step=s, strain=x), dict(sigma=q), 0.0) for s, x, q in steps]
    first = analysis_trigger(cfg)
    got = [first.fires(Clock(step=s, strain=x), dict(sigma=q), 0.0) for s, x, q in steps[:150]]
    ck = first.state()
    second = analysis_trigger(cfg)
    second.restore({k: np.int64(v) for k, v in ck.items()})     # as read back from HDF5
    got += [second.fires(Clock(step=s, strain=x), dict(sigma=q), 0.0) for s, x, q in steps[150:]]
    assert got == ref


def test_old_checkpoints_without_a_decade_restore_as_none():
    t = PerDecade("V2", 2)
    t.restore({"level": -10**9})
    assert t.level is None
    t.restore({})
    assert t.level is None
    t.restore({"level": 7})
    assert t.level == 7


def test_every_elapsed_and_wall():
    assert [s for s in range(10) if Every(3).fires(Clock(step=s), {}, 0)] == [0, 3, 6, 9]
    assert not any(Every(0).fires(Clock(step=s), {}, 0) for s in range(5))
    e = Elapsed(steps=4, seconds=10.0, start_step=2, start_time=0.0)
    fired = [s for s in range(3, 20) if e.fires(Clock(step=s), {}, now=0.5 * s)]
    assert fired == [6, 10, 14, 18]                    # 4 steps since the last, or 10 s
    e = Elapsed(steps=100, seconds=1.0, start_time=0.0)
    assert [s for s in range(1, 8) if e.fires(Clock(step=s), {}, now=0.4 * s)] == [3, 6]
    w = WallEvery(2.0)
    assert [t for t in (0.0, 1.0, 2.0, 3.5, 4.1) if w.fires(Clock(), {}, t)] == [0.0, 2.0, 4.1]


def test_combinators_and_printing():
    t = After(0.5, FirstOf(Never(), Every(2)))
    assert not t.fires(Clock(step=2, strain=0.4), {}, 0)
    assert t.fires(Clock(step=2, strain=0.6), {}, 0)
    assert analysis_trigger(dict(analysis_every=0, analysis_strain=0.0, analysis_per_decade=0.0,
                                 analysis_from_strain=0.0, analysis_quantity="V2")) == Never()
    assert "PerDecade" in repr(analysis_trigger(CFGS[0] | {"analysis_quantity": "V2"}))
    assert StrainEvery(0.1, 0.2) == StrainEvery(0.1, 0.2) != StrainEvery(0.1)


def test_clock_round_trip():
    c = Clock()
    c.advance(-0.01)
    c.advance(0.02)
    c.next_leg()
    c.advance(0.005)
    assert (c.step, c.leg, c.leg_steps) == (3, 1, 1)
    assert c.strain == pytest.approx(0.035) and c.leg_strain == pytest.approx(0.005)
    assert Clock.restore(c.state()) == c

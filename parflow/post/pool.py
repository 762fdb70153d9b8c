"""Pooled ensemble summaries (docs/ensembles.md "Pooling summaries"): the samples of several
ensembles of one scene -- run at different times, e.g. in sessions whose run files did not
survive -- as one summary, in the form and file format of ``post.ensemble``'s
``summary.h5``, so that ``python -m parflow.plot FOLDER`` draws it.

An ensemble's samples get their seeds from the scene's seed (docs/ensembles.md "The seed
rule"); more samples of the same scene are the same scene run again with another top-level
``seed``.  Pooling requires the same model and the same scene apart from its seed, title,
[ensemble] and [output] (``post.ensemble.scene_protocol``; summaries that do not record
their scene are refused), and no sample seed twice (the same realisation counted twice).

* ``samples``: the inputs' samples one after another (index = position in the pool; ``used``
  the positions of those that enter the statistics);
* ``scalars`` and ``fits``: the per-sample values concatenated (NaN for a sample whose
  summary lacks the name), then mean, standard error and count as in any summary;
* ``curves``: each input's per-sample rows; where the inputs' grids differ, interpolated
  onto one grid spanning all of them (log-spaced where the curve's x scale is log; log-log
  interpolation where both scales are, as the summaries build them;
  :data:`post.ensemble.GRID_POINTS` points), NaN outside a sample's own range; where every
  input has the same grid (the same bins), the rows as they are;
* ``ensemble_fits``: recomputed on the pooled data: the chain's <V^2> exponent of the
  averaged forward curve (``post.ensemble.chain_ensemble_fit``, the fit window from the
  samples' typical steps) with its jackknife error, and the jamming rate.

``python -m parflow.post.pool SUMMARY... --out FOLDER`` (a SUMMARY may be an ensemble folder:
its summary.h5) writes FOLDER/summary.h5 (recording the inputs) and prints the pooled counts.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from .ensemble import (GRID_POINTS, chain_ensemble_fit, check_poolable, jamming_rate, on_grid,
                       read_summary, scene_protocol, write_summary_file)


def _summary_path(p: str) -> str:
    return os.path.join(p, "summary.h5") if os.path.isdir(p) else p


def _values(section: dict, name: str, n: int) -> np.ndarray:
    q = section.get(name)
    return np.asarray(q["values"], float) if q is not None else np.full(n, np.nan)


def _grid(curves: list[dict]) -> np.ndarray:
    lo = min(float(np.nanmin(c["x"])) for c in curves)
    hi = max(float(np.nanmax(c["x"])) for c in curves)
    if curves[0].get("xscale") == "log":
        return np.geomspace(lo, hi, GRID_POINTS)
    return np.linspace(lo, hi, GRID_POINTS)


def pool_curves(curves: list[dict | None], n_used: list[int]) -> dict | None:
    """One curve from the inputs' (None: an input without it; n_used: each input's sample
    rows): every row on the common grid."""
    have = [c for c in curves if c is not None and np.size(c["x"]) >= 2]
    if not have:
        return None
    if all(c is not None and np.array_equal(c["x"], have[0]["x"]) for c in curves):
        # one grid already (the same bins, e.g. a suspension's P(f), or one input): rows as
        # they are, nothing interpolated
        first = have[0]
        return dict(x=np.asarray(first["x"], float),
                    values=np.vstack([np.atleast_2d(np.asarray(c["values"], float))
                                      for c in curves]),
                    **{a: str(first.get(a, "")) for a in ("xlabel", "ylabel", "xscale", "yscale")})
    grid = _grid(have)
    log = have[0].get("xscale") == "log" and have[0].get("yscale") == "log"
    rows = []
    for c, n in zip(curves, n_used):
        if c is None or np.size(c["x"]) < 2:
            rows.extend(np.full(grid.size, np.nan) for _ in range(n))
            continue
        vals = np.atleast_2d(np.asarray(c["values"], float))
        rows.extend(on_grid(c["x"], v, grid, log=log) for v in vals)
    first = have[0]
    return dict(x=grid, values=np.array(rows), **{a: str(first.get(a, "")) for a in
                                                 ("xlabel", "ylabel", "xscale", "yscale")})


def pool_summaries(paths) -> dict:
    """The pooled statistics of the summaries at ``paths`` (``post.ensemble.summarise``'s
    form, with ``sources``); ValueError naming the inputs that cannot be pooled."""
    files = [_summary_path(p) for p in paths]
    S = []
    for f in files:
        if not os.path.isfile(f):
            raise ValueError(f"{f}: no such summary (an ensemble folder's summary.h5, or the file)")
        S.append(read_summary(f))
    model = str(S[0]["attrs"].get("model", ""))
    if scene_protocol(str(S[0]["attrs"].get("scene", ""))) is None:
        raise ValueError(f"{files[0]}: the summary records no scene (made before 2026-12-03?): "
                         "write it again (python -m parflow.post.ensemble FOLDER) to pool it")
    for f, s in zip(files, S):
        if str(s["attrs"].get("model", "")) != model:
            raise ValueError(f"{files[0]} and {f}: different models "
                             f"({model}, {s['attrs'].get('model')}): pass summaries of one scene")
    check_poolable([(f, str(s["attrs"].get("scene", "")), np.asarray(s["samples"]["seed"]).tolist())
                    for f, s in zip(files, S)])
    n_used = [len(s["samples"]["used"]) for s in S]
    index_of = []                  # per input: its sample indices -> pooled positions
    status, seed, used, offset = [], [], [], 0
    for s in S:
        idx = np.asarray(s["samples"]["sample"]).tolist()
        pos = {k: offset + j for j, k in enumerate(idx)}
        status += [x.decode() if isinstance(x, bytes) else str(x) for x in s["samples"]["status"]]
        seed += np.asarray(s["samples"]["seed"]).tolist()
        used += [pos[int(k)] for k in np.asarray(s["samples"]["used"]).tolist()]
        index_of.append(pos)
        offset += len(idx)
    out = dict(model=model, index=np.arange(offset, dtype=np.int64), status=status,
               seed=np.array(seed, dtype=np.int64), used=np.array(used, dtype=np.int64),
               scene=str(S[0]["attrs"].get("scene", "")), sources=files)
    for section in ("scalars", "fits"):
        names = sorted({n for s in S for n in s[section]})
        out[section] = {n: np.concatenate([_values(s[section], n, k) for s, k in zip(S, n_used)])
                        for n in names}
    names = sorted({n for s in S for n in s["curves"]})
    out["curves"] = {}
    for n in names:
        c = pool_curves([s["curves"].get(n) for s in S], n_used)
        if c is not None:
            out["curves"][n] = c
    ens = {}
    if "V2_forward" in out["curves"]:
        ens.update(chain_ensemble_fit(out["curves"]["V2_forward"],
                                      out["fits"].get("dgamma_typical", [])))
    strain = out["scalars"].get("rate_strain", out["scalars"].get("final_strain"))
    if strain is not None:
        ens["jamming_rate"] = jamming_rate([status[k] for k in out["used"]], strain,
                                           out["scalars"].get("jammed_compressing"))
    out["ensemble_fits"] = ens
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m parflow.post.pool",
                                 description="pool the summaries of ensembles of one scene")
    ap.add_argument("summaries", nargs="+", metavar="SUMMARY",
                    help="summary.h5 files, or ensemble folders holding one")
    ap.add_argument("--out", required=True, metavar="FOLDER",
                    help="write FOLDER/summary.h5 (then: python -m parflow.plot FOLDER)")
    args = ap.parse_args(argv)
    try:
        s = pool_summaries(args.summaries)
        if os.path.abspath(_summary_path(args.out)) in map(os.path.abspath, s["sources"]):
            raise ValueError(f"--out {args.out}: that is one of the inputs; pool into another folder")
        os.makedirs(args.out, exist_ok=True)
        path = os.path.join(args.out, "summary.h5")
        write_summary_file(path, s)
    except (ValueError, OSError) as e:
        print(f"parflow.post.pool: {e}", file=sys.stderr)
        return 2
    print(f"parflow.post.pool: {len(s['index'])} samples ({len(s['used'])} used) from "
          f"{len(s['sources'])} summaries -> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Which modes of N carry the stress, along a run: ``python -m parflow.modes RUN.h5``.

For every snapshot of a bonded run (chain or network; a scene with
``observables.snapshot_every > 0``), with N = S S^T and the affine rates b at that state:

* ``lam`` (k lowest eigenvalues of N, ascending) and their eigenvectors psi_q, by scipy
  shift-and-invert at 0 (serial; for larger systems use ``python -m parflow.spectrum``);
* ``share``: the part of sigma Omega = b^T N^-1 b carried by mode q,
  (psi_q . b)^2 / lam_q / (b^T N^-1 b) (the shares of all modes sum to 1);
* ``pr_stress``: participation ratio of psi_q over the rods, (sum psi^2)^2 / (Nc sum psi^4);
* ``pr_motion``: participation ratio over the nodes of S^T psi_q, the velocity pattern of
  mode q (1 for a uniform field, ~ m/N for one spread over m nodes);
* ``pr_V``: participation ratio of the velocity V_na of the snapshot.

Near jamming one mode carries sigma (share_1 -> 1) and V = S^T psi_1 (psi_1 . b) / lam_1
follows its motion pattern.  Results go atomically to RUN.modes.h5 (one row per snapshot,
with step, gamma, direction, sigma) and a figure ``modes.png`` in RUN's plot directory.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import scipy.sparse.linalg as sla

from .geometry import cell_at, pair_geometry, rigidity_csr
from .io import RunFile, atomic_h5, check_output_path, read_run
from .state import InputError

MAX_RODS = 300_000          # scipy's serial shift-and-invert: beyond, parflow.spectrum


def participation(w: np.ndarray) -> float:
    """(sum |w_i|^2)^2 / (n sum |w_i|^4) over the rows i of w (n,) or (n, d)."""
    w2 = w ** 2 if w.ndim == 1 else np.einsum("id,id->i", w, w)
    den = w2.size * float(np.sum(w2 ** 2))
    return float(np.sum(w2) ** 2 / den) if den > 0 else float("nan")


def mode_table(n_unit: np.ndarray, b: np.ndarray, i: np.ndarray, j: np.ndarray, n_nodes: int,
               k: int = 3) -> dict:
    """The k lowest modes of N = S S^T for rod unit vectors ``n_unit`` (Nc, d) between nodes
    i and j, with the stress share of each for affine rates ``b`` (see the module)."""

    S = rigidity_csr(n_unit, i, j, n_nodes)
    N = (S @ S.T).tocsc()
    nc, d = n_unit.shape
    k = min(k, nc - 1)
    lu = sla.splu(N)
    lam, psi = sla.eigsh(N, k=k, sigma=0.0, which="LM",
                         OPinv=sla.LinearOperator(N.shape, matvec=lu.solve, dtype=float))
    order = np.argsort(lam)
    lam, psi = lam[order], psi[:, order]
    total = float(b @ lu.solve(b))
    share = (psi.T @ b) ** 2 / lam / total
    motion = [(S.T @ psi[:, q]).reshape(n_nodes, d) for q in range(k)]
    return dict(lam=lam, share=share, sigma_omega=total,
                pr_stress=np.array([participation(psi[:, q]) for q in range(k)]),
                pr_motion=np.array([participation(m) for m in motion]))


def analyse_run(path: str, k: int = 3, progress=None) -> dict:
    """Mode table of every snapshot of the bonded run file ``path`` (arrays, one row each)."""
    with RunFile(path) as run:
        f = run.h5
        if "initial" not in f or "bonds" not in f["initial"]:
            raise InputError(f"{path!r} is not a run of a bonded model (chain, network): "
                             f"no initial/bonds")
        snaps = run.snapshot_steps()
        if not snaps:
            raise InputError(f"{path!r} has no snapshots: run the scene with "
                             f"[observables] snapshot_every = n (a snapshot every n steps)")
        init = run.initial()
        bd = init["bonds"]
        nc = len(bd["i"])
        if k > nc - 1:
            raise InputError(f"--k {k}: the run has {nc} rods, so N has {nc} eigenvalues and "
                             f"the shift-and-invert solver finds at most Nc - 1 = {nc - 1} of them")
        if nc > MAX_RODS:
            raise InputError(f"{len(bd['i'])} rods: too many for the serial mode analysis "
                             f"(<= {MAX_RODS}); use python -m parflow.spectrum on single states")
        ts = run.timeseries()
        steps, sig, dirn = ts["step"], ts["sigma"], ts["direction"]
        h0, E = init["h0"], init["E"]
        rows = {q: [] for q in ("step", "gamma", "direction", "sigma", "lam", "share", "pr_stress",
                                "pr_motion", "pr_V")}
        for c, key in enumerate(snaps):
            g = run.snapshot(key)
            step, gamma = int(g["step"]), float(g["gamma"])
            s = g["s"]
            _, _, n, b = pair_geometry(s, cell_at(h0, E, gamma), E, bd["i"], bd["j"], bd["shift"])
            t = mode_table(n, b, bd["i"], bd["j"], s.shape[0], k)
            row = int(np.searchsorted(steps, step))
            rows["step"].append(step)
            rows["gamma"].append(gamma)
            rows["direction"].append(int(dirn[row]))
            rows["sigma"].append(float(sig[row]))
            for q in ("lam", "share", "pr_stress", "pr_motion"):
                rows[q].append(t[q])
            rows["pr_V"].append(participation(g["V_na"]) if "V_na" in g else float("nan"))
            if progress:
                progress(c + 1, len(snaps), step)
    return {q: np.array(v) for q, v in rows.items()}


def write(out: str, res: dict, attrs: dict) -> None:
    """The mode table, written whole or not at all (``io.atomic_h5``)."""
    with atomic_h5(out) as f:
        for q, v in res.items():
            f.create_dataset(q, data=v)
        f.attrs.update(attrs)


def plot(res: dict, png: str, title: str = "") -> None:
    # matplotlib only when a figure is drawn, and the Agg backend before pyplot
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .plot.base import save_figure
    fig, ax = plt.subplots(1, 3, figsize=(13, 4))
    for d, mk, lab in ((1, "o", "forward"), (-1, "s", "reverse")):
        m = res["direction"] == d
        if not np.any(m):
            continue
        x = res["sigma"][m]
        ax[0].semilogx(x, res["share"][m, 0], mk, ms=3, label=lab)
        if res["lam"].shape[1] > 1:
            ax[1].loglog(x, res["lam"][m, 1] / res["lam"][m, 0], mk, ms=3, label=lab)
        ax[2].loglog(x, res["pr_V"][m], mk, ms=3, label=f"V ({lab})")
        ax[2].loglog(x, res["pr_stress"][m, 0], mk, ms=3, mfc="none", label=f"mode 1 stress ({lab})")
    ax[0].set(xlabel="σ", ylabel="share of σ on the lowest mode")
    ax[1].set(xlabel="σ", ylabel="λ₂ / λ₁")
    ax[2].set(xlabel="σ", ylabel="participation ratio")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.suptitle(title or "modes along the run")
    fig.tight_layout()
    try:
        save_figure(fig, png, dpi=110)
    finally:
        plt.close(fig)


def _same_file(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m parflow.modes", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="a chain or network run file with snapshots")
    ap.add_argument("--k", type=int, default=3, help="lowest modes per snapshot (default 3)")
    ap.add_argument("--output", default=None, help="HDF5 output (default RUN.modes.h5)")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    ap.add_argument("--no-plot", action="store_true", help="do not draw modes.png")
    a = ap.parse_args(argv)
    prog = "parflow.modes"
    try:
        if a.k < 1:
            raise InputError(f"--k must be >= 1, got {a.k}")
        if a.output is not None and not a.output.strip():
            raise InputError("--output is empty: give a file name, or drop --output to write "
                             "RUN.modes.h5")
        out = a.output or os.path.splitext(a.run)[0] + ".modes.h5"
        if os.path.exists(a.run) and _same_file(a.run, out):
            raise InputError(f"--output {out!r} is the run file itself: choose another file")
        read_run(a.run).close()             # the input first: no folder made for a missing run
        check_output_path(out, a.overwrite)

        def progress(c, n, step):
            if c % 20 == 0 or c == n:
                print(f"{prog}: {c}/{n} snapshots (step {step})", file=sys.stderr, flush=True)
        res = analyse_run(a.run, a.k, progress)
    except InputError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    write(out, res, dict(source=os.path.abspath(a.run), k=a.k, command=" ".join(sys.argv)))
    print(f"{prog}: wrote {out} ({len(res['step'])} snapshots)")
    if not a.no_plot:
        from .plot import default_outdir     # (matplotlib only when a figure is drawn)
        d = default_outdir(a.run)
        os.makedirs(d, exist_ok=True)
        png = os.path.join(d, "modes.png")
        plot(res, png, os.path.basename(a.run))
        print(f"{prog}: wrote {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

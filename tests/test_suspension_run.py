"""The suspension through the scene driver (parflow.shear): legs in both directions, HDF5
output, analyses on the frozen contact network (omega_min, point response, delta_gamma),
restart, 1 rank vs 2 ranks, bad scenes."""
import os

import h5py
import numpy as np
import pytest
from petsc4py import PETSc

from parflow.models import chain
from parflow.models import frozen as fz
from parflow.models import suspension as msu
from parflow.scene import load_scene
from parflow.state import InputError
from parflow.dynamics.bonded import BondedSystem
from systems import run_scene


def susp_scene(path, N=192, phi=0.80, fwd=0.08, rev=0.03, extra="", model="",
               obs="analysis_strain = 0.04"):
    return load_scene(f"""
seed = 3
[model]
name = "suspension"
N = {N}
phi = {phi}
response_rods = 3
{model}
[[protocol.leg]]
direction = "forward"
strain = {fwd}
[[protocol.leg]]
direction = "reverse"
strain = {rev}
[observables]
{obs}
[output]
path = "{path}"
checkpoint_every = 4
{extra}
""")


def test_suspension_scene_forward_and_reverse(comm, mpi_tmp_path):
    path = str(mpi_tmp_path / "susp.h5")
    assert run_scene(susp_scene(path)) == "complete"
    comm.barrier()
    with h5py.File(path) as f:                      # every rank reads and asserts
        assert f.attrs["engine"] == "contacts" and f.attrs["model"] == "suspension"
        assert f.attrs["max_overlap"] <= 1e-9
        ts = f["timeseries"]
        g, dg, d = ts["gamma"][:], ts["dgamma"][:], ts["direction"][:]
        np.testing.assert_allclose(np.diff(g), dg[1:], rtol=0, atol=1e-14)
        assert np.all(dg[1:] * d[1:] > 0)           # steps go the way of their leg
        assert g[-1] == pytest.approx(0.08 - 0.03, abs=1e-12)
        assert np.all(ts["sigma"][:] > 0) and np.all(ts["pressure"][:] > 0)
        assert np.max(ts["overlap"][:]) <= 1e-9
        # sigma = |V_na|^2/Omega = -<f|b>/Omega + gap work (complementarity, DESIGN §5),
        # on every row: the first one reports the forces (and gap work) of the first step
        s_id = ts["sigma_fb"][:] + ts["gap_work"][:]
        np.testing.assert_allclose(s_id, ts["sigma"][:], rtol=1e-6)
        groups = sorted(f["analysis"])
        assert len(groups) >= 3
        for k in groups:
            a = f["analysis"][k]
            assert a.attrs["frozen_error"] == ""
            assert a.attrs["frozen_omega_min"] > 0
            assert 0 < a.attrs["delta_gamma_reached"] <= a.attrs["delta_gamma"] < 1.0
            assert a.attrs["delta_gamma_stop"] in ("target", "jammed")
            # P(f/<f>) is a density of the force-bearing contacts
            w = np.diff(a["force_edges"][:]) * a["force_P"][:]
            assert np.nansum(w) == pytest.approx(1.0, abs=1e-3)
            assert a["corr_C"].shape == a["corr_r"].shape
            assert np.isfinite(a.attrs["resp_l_c"])


def test_restart_equals_uninterrupted(comm, mpi_tmp_path):
    full = str(mpi_tmp_path / "sfull.h5")
    part = str(mpi_tmp_path / "spart.h5")
    run_scene(susp_scene(full))
    assert run_scene(susp_scene(part), max_steps=9) == "budget"
    comm.barrier()
    scene = load_scene(susp_scene(part)["text"])
    scene["output"]["path"] = part
    assert run_scene(scene, restart=True, max_steps=10**6) == "complete"
    comm.barrier()
    with h5py.File(full) as a, h5py.File(part) as b:
        assert a["timeseries/step"].shape == b["timeseries/step"].shape
        for q in ("gamma", "sigma", "dgamma", "n_active", "collisions"):
            np.testing.assert_array_equal(a["timeseries"][q][:], b["timeseries"][q][:])
        np.testing.assert_array_equal(a["checkpoint/s"][:], b["checkpoint/s"][:])
        assert b.attrs["restarted_at_step"] == 9
    comm.barrier()


def test_two_ranks_equal_one_rank(comm, mpi_tmp_path):
    if comm.size == 1:
        pytest.skip("compares 1 rank with several: run under mpirun -n 2")
    p_world = str(mpi_tmp_path / "sworld.h5")
    p_self = str(mpi_tmp_path / f"sself{comm.rank}.h5")
    run_scene(susp_scene(p_world), PETSc.COMM_WORLD)
    run_scene(susp_scene(p_self), PETSc.COMM_SELF)
    comm.barrier()
    with h5py.File(p_world) as a, h5py.File(p_self) as b:
        assert a.attrs["n_ranks"] == comm.size
        for q in ("gamma", "sigma", "pressure", "n_active"):
            np.testing.assert_array_equal(a["timeseries"][q][:], b["timeseries"][q][:])
        for k in a["analysis"]:
            for q in ("delta_gamma", "frozen_omega_min"):
                assert a["analysis"][k].attrs[q] == pytest.approx(b["analysis"][k].attrs[q], rel=1e-9)
    comm.barrier()


def test_compressing_scene_restart_equals_uninterrupted(comm, mpi_tmp_path):
    """A scene that compresses while it shears: phi per row (clipped at compress_to during
    the reverse leg), in the checkpoint, and a restart mid-compression = uninterrupted."""
    model = "compress_rate = 0.2\ncompress_to = 0.82"
    full = str(mpi_tmp_path / "cfull.h5")
    part = str(mpi_tmp_path / "cpart.h5")
    assert run_scene(susp_scene(full, model=model, obs="")) == "complete"
    assert run_scene(susp_scene(part, model=model, obs=""), max_steps=9) == "budget"
    comm.barrier()
    scene = load_scene(susp_scene(part, model=model, obs="")["text"])
    assert run_scene(scene, restart=True, max_steps=10**6) == "complete"
    comm.barrier()
    with h5py.File(full) as a, h5py.File(part) as b:
        ts = a["timeseries"]
        g, phi = ts["gamma"][:], ts["phi"][:]
        applied = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(g)))])
        np.testing.assert_allclose(phi, np.minimum(0.80 + 0.2 * applied, 0.82), rtol=0, atol=1e-12)
        assert phi[-1] == 0.82 and a["checkpoint"].attrs["phi"] == 0.82
        assert a.attrs["max_overlap"] <= 1e-9
        np.testing.assert_allclose(ts["sigma_fb"][:] + ts["gap_work"][:], ts["sigma"][:], rtol=1e-6)
        for q in ("gamma", "sigma", "phi", "n_active"):
            np.testing.assert_array_equal(ts[q][:], b["timeseries"][q][:])
        np.testing.assert_array_equal(a["checkpoint/s"][:], b["checkpoint/s"][:])
    # the statistics belong to the phi of their window (the forward rows of the last half of
    # the run's strain here: part of the compression, whose range the fits record), not to
    # the scene's starting phi
    from parflow.post.runs import load
    from parflow.post.suspension import suspension_fits, window_rows
    run = load(full)
    fits = suspension_fits(run)
    m = window_rows(run)
    w = np.abs(run.ts["dgamma"][m])
    assert fits["phi_range"] == (run.ts["phi"][m].min(), run.ts["phi"][m].max())
    assert fits["phi_range"][0] > 0.81 and fits["phi_range"][1] == pytest.approx(0.816, abs=1e-12)
    assert fits["phi"] == pytest.approx(np.sum(w * run.ts["phi"][m]) / np.sum(w), rel=1e-14)
    comm.barrier()


@pytest.mark.parametrize("params, msg", [
    (dict(compress_rate=0.1), "go together"), (dict(compress_to=0.83), "go together"),
    (dict(compress_rate=0.1, compress_to=0.79), "above model.phi"),
])
def test_bad_compression(params, msg):
    with pytest.raises(InputError, match=msg):
        msu.build(dict(N=64, phi=0.80, **params), 1)


@pytest.mark.parametrize("model, msg", [
    ("phi = 0.85", "phi_J"),
    ("compress_to = 0.9", "compress_to"),
    ("compress_rate = 2.0", "compress_rate"),
    ("ratio = 0.0", "ratio"),
    ("small_fraction = 1.5", "small_fraction"),
    ("factor = 'lu'", "factor"),
])
def test_bad_scene(model, msg, tmp_path):
    text = susp_scene(str(tmp_path / "x.h5"))["text"]
    text = text.replace("phi = 0.8\n", "").replace("[model]\n", f"[model]\n{model}\n")
    with pytest.raises(InputError, match=msg):
        load_scene(text)


def test_delta_gamma_finds_the_chain_jamming_strain():
    """On a system whose jamming strain is exact -- the chain, gamma_c = ln(N a0 / Lx(0)) --
    the backward shear of delta_gamma (direction -1: shear with +1) stops just short of it."""
    st = chain.build(dict(N=200, epsilon=0.1, mu=0), seed=5)
    scene = load_scene('[model]\nname = "chain"\n[[protocol.leg]]\ndirection = "forward"\n'
                       'strain = 1\n')
    sysm = BondedSystem(PETSc.COMM_SELF, st)
    try:
        F0 = sysm.evaluate(st.s, 0.0)
        factor = 1e6
        out = fz.delta_gamma(sysm, st, F0, -1, scene, factor, max_strain=1.0)
    finally:
        sysm.destroy()
    gc = st.meta["gamma_c"]
    assert out["delta_gamma_stop"] in ("target", "jammed")
    # chain: sigma ~ (gamma_c - gamma)^-3 near jamming, so at sigma = factor sigma_0 the
    # distance left is ~ gamma_c factor^(-1/3); the extrapolation only gets closer
    assert gc * (1 - 3 * factor ** (-1 / 3)) < out["delta_gamma_reached"] < gc
    assert abs(out["delta_gamma"] - gc) <= abs(out["delta_gamma_reached"] - gc)


def test_freeze_keeps_force_bearing_contacts():
    from parflow.dynamics.engines import ContactEngine
    state = msu.make_suspension(128, 0.80, seed=2)
    scene = load_scene('[model]\nname = "suspension"\nN = 128\n[[protocol.leg]]\n'
                       'direction = "forward"\nstrain = 1\n')
    eng = ContactEngine(PETSc.COMM_SELF, state, scene, msu)
    for _ in range(20):
        eng.step(1, None)
    F = eng.probe()
    frozen = fz.freeze(eng.state, F)
    fb = msu.force_bearing(F.f)
    assert len(frozen.bonds) == int(fb.sum()) > 0
    r = (frozen.s[frozen.bonds.j] + frozen.bonds.shift - frozen.s[frozen.bonds.i]) @ frozen.h.T
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), frozen.bonds.l0, rtol=1e-13)
    # contacts carrying force are closed: rest length = R_i + R_j up to the LCP's gaps
    R = eng.state.radii
    assert np.all(frozen.bonds.l0 >= (R[frozen.bonds.i] + R[frozen.bonds.j]) * (1 - 1e-9))


def test_configuration_file(tmp_path, comm):
    """A user configuration runs; one with an overlap is refused with the pair named."""
    st = msu.make_suspension(64, 0.78, seed=4)
    X = st.s @ st.h.T
    box = np.diag(st.h0)
    good = str(tmp_path / f"good{comm.rank}.npz")
    np.savez(good, positions=X, radii=st.radii, box=box)
    model = f'configuration_file = "{good}"'
    text = susp_scene(str(tmp_path / "c.h5"), N=64, phi=st.meta["phi"], model=model)["text"]
    state = msu.build(load_scene(text)["model"], 1)
    np.testing.assert_allclose(state.s, st.s, atol=1e-14)
    bad = str(tmp_path / f"bad{comm.rank}.npz")
    X2 = X.copy()
    i, j = 0, int(np.argmin(np.linalg.norm(X[1:] - X[0], axis=1))) + 1
    X2[j] = X2[i] + 0.5 * (st.radii[i] + st.radii[j]) * np.array([1.0, 0.0])
    np.savez(bad, positions=X2, radii=st.radii, box=box)
    with pytest.raises(InputError, match="overlapping"):
        msu.build(load_scene(text.replace(good, bad))["model"], 1)
    with pytest.raises(InputError, match="does not match the scene"):
        msu.build(load_scene(text.replace("N = 64", "N = 65"))["model"], 1)


def test_cli_bad_scene_writes_nothing(tmp_path, comm, capsys):
    from parflow.shear import main
    out = tmp_path / f"bad{comm.rank}.h5"
    scene = tmp_path / f"bad{comm.rank}.toml"
    scene.write_text(susp_scene(str(out))["text"].replace("phi = 0.8\n", "phi = 0.9\n"))
    assert main([str(scene), "--no-plots"]) == 2
    assert not out.exists() and not (tmp_path / f"bad{comm.rank}.h5.tmp").exists()


def test_suspension_figures(comm, mpi_tmp_path):
    """Every suspension figure is drawn from small runs (the across-phi ones from two runs),
    and the pooled fits see every analysis instant."""
    from parflow import plot
    paths = []
    for phi in (0.78, 0.80):
        path = str(mpi_tmp_path / f"fig_{phi}.h5")
        scene = susp_scene(path, phi=phi, fwd=0.12, rev=0.01,
                           obs="analysis_strain = 0.03\nanalysis_from_strain = 0.03")
        run_scene(scene)
        paths.append(path)
    comm.barrier()
    out = str(mpi_tmp_path / f"plots{comm.rank}")
    res = plot.make_plots(paths[1], outdir=out)
    names = {s.name for s in plot.FIGURES if s.models == {"suspension"}}
    drawn = {os.path.splitext(os.path.basename(p))[0] for p in res.written}
    assert names - {"fig6b_relaxation"} <= drawn, (res.skipped, res.failed)
    assert not res.failed
    acr = plot.make_across_plots(paths, outdir=out)
    across = {s.name for s in plot.ACROSS_FIGURES if s.models == {"suspension"}}
    assert across <= {os.path.splitext(os.path.basename(p))[0]
                      for p in acr.written}, (acr.skipped, acr.failed)
    ac = acr.fits["across"]
    n_inst = sum(1 for p in paths for a in plot.load_run(p).analysis
                 if np.isfinite(a["delta_gamma"]) and a["sigma"] > 0)
    assert ac["delta_gamma"]["n"] == n_inst >= 4
    assert any("delta_gamma" in line for line in plot.format_fits(acr.fits))
    comm.barrier()


def test_fit_phi_c_recovers_a_divergence():
    from parflow.post.suspension import fit_phi_c
    phi = np.array([0.80, 0.81, 0.82, 0.825, 0.83, 0.835])
    sigma = 0.02 * (0.843 - phi) ** -2.1
    f = fit_phi_c(phi, sigma)
    assert f["phi_c"] == pytest.approx(0.843, abs=2e-4) and f["beta"] == pytest.approx(2.1, abs=0.02)
    assert np.isnan(fit_phi_c(phi[:3], sigma[:3])["phi_c"])

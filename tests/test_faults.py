"""Faults: a full disk, kill -9, a checkpoint's durability, and what a flush costs.

The guarantees tested here are stated in docs/output.md "Faults": the file named FILE is
always a complete, closed run file (a flush never writes it in place); a checkpoint is on
disk when it is taken; a full disk ends the run with one line, exit 1, status "failed" when
it can still be written, and no temporary left; a flush writes what it appends, not the
whole file."""
import errno
import os
import random
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import h5py
import numpy as np
import pytest

from parflow import io
from parflow.io import writer as io_writer
from parflow.io import RunWriter, load_group, read_run
from hang_guard import guard

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# -- the writer alone (in-process; every rank writes its own file under mpirun) ----------


def dump(path) -> dict:
    """Every dataset and attribute of an HDF5 file, by path: what a reader can see."""
    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            out[name + "@"] = {k: np.asarray(v).tolist() if not isinstance(v, str) else v
                               for k, v in sorted(obj.attrs.items())}
            if isinstance(obj, h5py.Dataset):
                out[name] = obj[()]
        visit("", f)
        f.visititems(visit)
    return out


def assert_same(a: dict, b: dict):
    assert sorted(a) == sorted(b)
    for k in a:
        if isinstance(a[k], np.ndarray):
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        else:
            assert a[k] == b[k], k


def feed(w: RunWriter, n_flushes: int, n: int = 5000, seed: int = 0):
    """A run's worth of writes: rows (with a quantity appearing late), analyses, snapshots,
    a checkpoint and attributes at every flush; the rows cross chunk boundaries."""
    rng = np.random.default_rng(seed)
    w.create(dict(status="running", scene="x = 1\n"),
             {"initial": (dict(s=rng.random((n, 2)), bonds=dict(i=np.arange(n))), {})})
    step = 0
    for k in range(n_flushes):
        for _ in range(1500):
            row = dict(step=step, gamma=1e-3 * step, sigma=rng.random())
            if k >= 2:
                row["omega_min"] = rng.random()
            w.append(row)
            step += 1
        last = step - 1
        w.add_group(f"snapshots/{last:08d}", dict(s=rng.random((n, 2)), tau=rng.random(n)),
                    dict(step=last))
        if k % 2:
            w.add_group(f"analysis/{last:08d}", dict(C_n=rng.random(n // 2)), dict(step=last, l=1.5))
        w.set_checkpoint(dict(s=rng.random((n, 2)), keys=np.arange(rng.integers(1, n))),
                         dict(step=last, n_rows=step))
        w.set_attrs(steps=last, message=f"flush {k}")
        w.flush(force=True)
        yield step


def test_flush_appends_without_copying_and_keeps_the_layout(tmp_path):
    """A flush writes what it appends (the file is copied once, at the first flush); after
    every flush FILE and its twin hold the same data as the old copy-everything scheme, and
    the finished file is the same to a reader (read_run, load_group)."""
    new, old = RunWriter(str(tmp_path / "new.h5")), RunWriter(str(tmp_path / "old.h5"), shadow=False)
    for _ in zip(feed(new, 6), feed(old, 6)):
        ref = dump(old.path)
        assert_same(dump(new.path), ref)
        assert_same(dump(new.tmp), ref)           # the twin, ready for the next flush
    assert new.copies == 1 and old.copies == 6
    for w in (new, old):
        assert w.close(status="complete", message="done") is None
        assert os.listdir(tmp_path).count(os.path.basename(w.path)) == 1
    assert sorted(os.listdir(tmp_path)) == ["new.h5", "old.h5"]      # no temporaries left
    assert_same(dump(new.path), dump(old.path))
    with read_run(new.path) as f:
        assert f.attrs["status"] == "complete" and f["timeseries/step"].shape == (9000,)
        np.testing.assert_array_equal(f["timeseries/step"][:], np.arange(9000))
        assert np.isnan(f["timeseries/omega_min"][:3000]).all()
        ck = load_group(f["checkpoint"])
        assert ck["s"].shape == (5000, 2) and f["checkpoint"].attrs["n_rows"] == 9000


def test_reservation_bounds_what_a_batch_adds(tmp_path, monkeypatch):
    """Before HDF5 writes a batch, the space it can take is allocated (so that a full disk
    is a clean error before any write): the estimate bounds what the file really grows."""
    w = RunWriter(str(tmp_path / "r.h5"), shadow=False)
    sizes = []
    real = io_writer._allocate

    def allocate(path, need, new=False):
        sizes.append((os.path.getsize(path), need))
        real(path, need, new)
    monkeypatch.setattr(io_writer, "_allocate", allocate)
    grown = []
    for _ in feed(w, 5, n=20000):
        grown.append(os.path.getsize(w.path) - sizes[-1][0])
    w.append(dict(step=1, gamma=0.0, sigma=0.0, **{f"q{k}": 1.0 for k in range(30)}))
    w.set_attrs(message="x" * 5000, scene="y" * 20000)
    w.flush()
    grown.append(os.path.getsize(w.path) - sizes[-1][0])
    assert len(grown) == len(sizes) == 6
    for g, (_, need) in zip(grown, sizes):
        assert 0 < g <= need, list(zip(grown, sizes))


def test_full_disk_leaves_file_and_twin_intact(tmp_path, monkeypatch):
    """The reservation meets the full disk: OSError before any write, FILE unchanged byte
    for byte, the pending data still pending, the twin still good (no copy needed when
    space comes back); the status alone can then be written."""
    w = RunWriter(str(tmp_path / "f.h5"))
    gen = feed(w, 10)
    next(gen)
    next(gen)
    before = open(w.path, "rb").read()
    real = os.posix_fallocate

    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    monkeypatch.setattr(os, "posix_fallocate", full)
    with pytest.raises(OSError) as exc:
        next(gen)
    assert "no space left on the device" in io.write_failure(w.path, exc.value)
    assert open(w.path, "rb").read() == before and w.n_rows == 3000 and w.pending_rows == 1500
    assert not os.path.exists(w.prev)
    monkeypatch.setattr(os, "posix_fallocate", real)
    w.flush()
    assert w.copies == 1 and w.n_rows == 4500
    monkeypatch.setattr(os, "posix_fallocate", full)
    w.append(dict(step=4500, gamma=0.0, sigma=0.0))
    assert "status could not be written" in w.close(status="failed", message="disk full")
    monkeypatch.setattr(os, "posix_fallocate", real)
    w.append(dict(step=4500, gamma=0.0, sigma=0.0))
    assert w.close(data=False, status="failed", message="disk full") is None
    with read_run(w.path) as f:
        assert f.attrs["status"] == "failed" and f["timeseries/step"].shape == (4500,)
    assert sorted(os.listdir(tmp_path)) == ["f.h5"]


def test_without_hard_links_every_flush_copies(tmp_path, monkeypatch):
    """A file system without hard links: each flush copies FILE (the old scheme), with the
    same result."""
    def no_links(*a, **k):
        raise OSError(errno.EPERM, "no hard links")
    monkeypatch.setattr(os, "link", no_links)
    w, ref = RunWriter(str(tmp_path / "a.h5")), RunWriter(str(tmp_path / "b.h5"), shadow=False)
    for _ in zip(feed(w, 3), feed(ref, 3)):
        assert_same(dump(w.path), dump(ref.path))
    assert w.copies == 3 and not os.path.exists(w.tmp) and not os.path.exists(w.prev)


# -- whole runs in their own processes ---------------------------------------------------

CHAIN = """
seed = 1
[model]
name = "chain"
N = {N}
epsilon = 0.1
mu = 0
[[protocol.leg]]
direction = "forward"
V2_above = 1e12
[output]
checkpoint_every = {ck}
flush_seconds = {flush}
[observables]
snapshot_every = {snap}
"""


def shear_cmd(*args, mpi=0):
    cmd = [sys.executable, "-m", "parflow.shear", *map(str, args)]
    return ([shutil.which("mpirun") or "mpirun", "-n", str(mpi)] if mpi else []) + cmd


def env():
    return dict(os.environ, PYTHONPATH=ROOT)


def run(*args, mpi=0, timeout=120):
    return subprocess.run(shear_cmd(*args, mpi=mpi), capture_output=True, text=True,
                          timeout=guard(timeout), env=env())


def scene(tmp_path, N=3000, ck=5, flush=1000, snap=0, name="s.toml"):
    p = tmp_path / name
    p.write_text(CHAIN.format(N=N, ck=ck, flush=flush, snap=snap))
    return p


def check_consistent(path) -> tuple[int, int]:
    """FILE opens as a run file; every column has the same rows; the step column is 0..n-1;
    every group loads; a checkpoint (if any) matches the rows.  Returns (rows, checkpoint
    step or -1)."""
    with read_run(str(path)) as f:
        ts = f["timeseries"]
        n = ts["step"].shape[0] if "step" in ts else 0
        assert all(ts[k].shape == (n,) for k in ts)
        np.testing.assert_array_equal(ts["step"][:] if n else [], np.arange(n))
        for g in ("snapshots", "analysis"):
            for key in f.get(g, {}):
                load_group(f[g][key])
                assert int(f[g][key].attrs["step"]) <= n - 1
        if "checkpoint" not in f:
            return n, -1
        ck = f["checkpoint"].attrs
        assert 1 <= ck["n_rows"] <= n and int(ts["step"][ck["n_rows"] - 1]) == ck["step"]
        load_group(f["checkpoint"])
        return n, int(ck["step"])


def assert_one_line(res, prefix, *fragments):
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith(prefix)]
    assert len(lines) == 1, res.stderr
    assert "Traceback" not in res.stderr and "MPI_ABORT" not in res.stderr, res.stderr
    for frag in fragments:
        assert frag in lines[0], lines[0]


def restart_works(path, tmp_path, extra=5):
    """--restart continues the file from its checkpoint (on a copy, if asked)."""
    with h5py.File(path) as f:
        ck_step = int(f["checkpoint"].attrs["step"])
    res = run("--restart", path, "--max-steps", ck_step + extra, "--quiet", "--no-plots")
    assert res.returncode == 0, res.stderr
    with read_run(str(path)) as f:
        assert f.attrs["status"] == "budget" and f["timeseries/step"][-1] == ck_step + extra
    assert check_consistent(path)[0] == ck_step + extra + 1
    assert not os.path.exists(f"{path}.tmp") and not os.path.exists(f"{path}.prev")


@pytest.fixture
def small_disk(tmp_path):
    """An 8 MB tmpfs (root: mount), unmounted afterwards; None where mounting is not
    possible (the test then fakes the full disk in the writer's process)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    ok = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(mnt)],
                        capture_output=True).returncode == 0 if shutil.which("mount") else False
    try:
        yield mnt if ok else None
    finally:
        if ok:
            subprocess.run(["umount", str(mnt)], check=True)


FAKE_FULL_DISK = textwrap.dedent("""
    import errno, os, sys
    real = os.posix_fallocate
    def fallocate(fd, offset, length):   # an 8 MB disk holding only this run's files
        folder = os.path.dirname(os.readlink(f"/proc/self/fd/{fd}"))
        used = sum(os.path.getsize(os.path.join(folder, n)) for n in os.listdir(folder))
        if used + length > 8 << 20:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd, offset, length)
    os.posix_fallocate = fallocate
    from parflow.shear import main
    sys.exit(main(sys.argv[1:]))
""")


@pytest.mark.serial_only
@pytest.mark.parametrize("mpi", [0, 2])
def test_disk_full_mid_run(tmp_path, small_disk, mpi):
    """The output folder fills up (an 8 MB tmpfs; each flush adds ~0.7 MB of snapshots):
    one line naming the full disk, exit 1 on every rank, no traceback or MPI abort; the
    file is the last good flush, with status "failed" and the reason, its checkpoint
    matching its rows, no temporary left beside it; --restart continues it elsewhere."""
    folder = small_disk or (tmp_path / "disk")
    out = folder / "o.h5"
    args = [scene(tmp_path, snap=1), "--output", out, "--no-plots", "--quiet"]
    if small_disk is not None:
        res = run(*args, mpi=mpi, timeout=180)
    else:
        cmd = shear_cmd(*args, mpi=mpi)
        k = cmd.index("-m")
        cmd[k:k + 2] = ["-c", FAKE_FULL_DISK]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=guard(180), env=env())
    assert res.returncode == 1, res.stderr
    assert_one_line(res, "parflow.shear: write error:", "no space left on the device",
                    repr(str(out)), "the file keeps the run up to step")
    assert sorted(os.listdir(folder)) == ["o.h5"]
    n, ck = check_consistent(out)
    with read_run(str(out)) as f:
        assert f.attrs["status"] == "failed"
        assert "no space left on the device" in f.attrs["message"]
        assert f.attrs["steps"] == n - 1 == ck and n > 10
    copy = tmp_path / "copy.h5"
    shutil.copyfile(out, copy)
    restart_works(copy, tmp_path)


def start(tmp_path, text, mpi=0):
    out = tmp_path / "o.h5"
    p = tmp_path / "s.toml"
    p.write_text(text)
    proc = subprocess.Popen(shear_cmd(p, "--output", out, "--no-plots", "--quiet", "--overwrite",
                                      mpi=mpi),
                            env=env(), stderr=subprocess.DEVNULL, start_new_session=True)
    return proc, out


def session(sid: int) -> list[int]:
    """The processes of session ``sid`` (the run started with start_new_session: mpirun
    and its ranks, which mpirun puts in process groups of their own)."""
    pids = []
    for d in os.listdir("/proc"):
        try:
            with open(f"/proc/{d}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
        except (OSError, IndexError, ValueError):
            continue
        if d.isdigit() and int(fields[3]) == sid and fields[0] != "Z":   # (not zombies)
            pids.append(int(d))
    return pids


def kill9(proc):
    """SIGKILL, at once, to the run and everything it started (mpirun and its ranks)."""
    for pid in session(proc.pid):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    proc.wait(timeout=guard(30))
    deadline = time.time() + 30
    while session(proc.pid) and time.time() < deadline:     # the ranks are gone too
        time.sleep(0.05)
    assert not session(proc.pid)


@pytest.mark.serial_only
@pytest.mark.parametrize("mpi", [0, 2])
def test_checkpoint_is_on_disk_when_taken(tmp_path, mpi):
    """checkpoint_every = 10 with flush_seconds = 1000 (no timed flush before the kill):
    each checkpoint is flushed as it is taken, so after kill -9 the file holds the last
    checkpoint and exactly the rows up to it, and --restart continues from it."""
    proc, out = start(tmp_path, CHAIN.format(N=3000, ck=10, flush=1000, snap=0), mpi=mpi)
    try:
        deadline, ck = time.time() + 90, -1
        while time.time() < deadline and ck < 30:
            time.sleep(0.2)
            try:
                with h5py.File(out, "r") as f:
                    ck = int(f["checkpoint"].attrs["step"]) if "checkpoint" in f else -1
            except (OSError, KeyError):
                pass
    finally:
        kill9(proc)
    assert ck >= 30, "no checkpoint reached the file"
    n, ck = check_consistent(out)
    assert ck >= 30 and ck % 10 == 0 and n == ck + 1
    with read_run(str(out)) as f:
        assert f.attrs["status"] == "running"
    restart_works(out, tmp_path)


@pytest.mark.serial_only
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_kill9_at_random_moments_leaves_a_readable_file(tmp_path, seed):
    """kill -9 at a random moment of a run that flushes all the time (every 0.02 s, a
    checkpoint every 3 steps, a snapshot every 2): FILE always opens, its columns agree,
    its groups load, its checkpoint matches its rows, and --restart continues it."""
    rng = random.Random(seed)
    proc, out = start(tmp_path, CHAIN.format(N=2000, ck=3, flush=0.02, snap=2))
    try:
        deadline = time.time() + 60
        while not out.exists() and time.time() < deadline:
            time.sleep(0.02)
        time.sleep(rng.uniform(0.2, 2.0))
    finally:
        kill9(proc)
    n, ck = check_consistent(out)
    if ck < 0:          # killed before the first checkpoint: nothing to restart
        assert n <= 4
        return
    restart_works(out, tmp_path)


@pytest.mark.serial_only
def test_reader_holding_the_file_keeps_its_view(tmp_path):
    """A reader that holds FILE open across flushes sees the file it opened, unchanged (the
    old FILE would be the next twin: HDF5's file lock refuses the writer, which then
    copies FILE instead)."""
    w = RunWriter(str(tmp_path / "r.h5"))
    gen = feed(w, 4)
    next(gen)
    next(gen)
    reader = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import sys, h5py
        f = h5py.File({w.path!r}, "r")
        n = f["timeseries/step"].shape[0]
        print(n, flush=True)
        sys.stdin.readline()
        assert f["timeseries/step"].shape[0] == n and (f["timeseries/step"][:] == range(n)).all()
        assert len(f["snapshots"]) == 2 and f["checkpoint"].attrs["n_rows"] == n
        print("same", flush=True)
    """)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env())
    assert int(reader.stdout.readline()) == 3000
    next(gen)                          # the twin is the reader's file: refused, dropped
    next(gen)                          # copies FILE
    out, _ = reader.communicate("go\n", timeout=guard(30))
    assert reader.returncode == 0 and out.strip() == "same"
    assert w.copies == 2
    assert w.close(status="complete") is None
    assert check_consistent(w.path) == (6000, 5999)

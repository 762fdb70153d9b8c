"""Ensembles: many samples of one scene in one MPI job (docs/ensembles.md).

``mpirun -n P python -m parflow.shear scene.toml --samples K [--ranks-per-sample r]`` (or an
[ensemble] table in the scene): COMM_WORLD is split into P / r groups of r consecutive ranks
(``algebra.comm.split_world``); each group runs samples one after the other, each an ordinary
:class:`parflow.run.Run` on the group's communicator writing its own run file
``FOLDER/sample_0007.h5`` (root attributes ``sample`` and ``sample_seed``).

*The seed rule.*  Sample k's seed is :func:`sample_seed` (seed, k) =
``SeedSequence(seed, spawn_key=(k,)).generate_state(1, uint64)[0] >> 1`` (numpy; the same
seed as ``SeedSequence(seed).spawn(K)[k]``, 63 bits so that it is a TOML integer): it depends
on the scene's seed and on k only, never on P, r or the order in which samples ran.  Sample 0
does not keep the scene's seed.  The sample's scene text is the ensemble's with its top-level
``seed`` line replaced (:func:`sample_text`), so a sample file is an ordinary run file: it
restarts and plots on its own.

*The queue* is dynamic and needs no messages: the leader (rank 0) of a group that is free
claims the lowest sample index not yet claimed by creating ``FOLDER/.claims/0007`` with
O_CREAT | O_EXCL (atomic on a filesystem every rank sees, as the output folder must be) and
broadcasts it to its group.  No rank waits for another group until the end, so a sample that
fails, jams or runs long holds up nobody.

*Failures.*  Whatever one sample raises (InputError, SolveError, WriteError, any exception)
is caught in its group and recorded as status ``failed`` with its message; the group goes on
with the next sample.  On groups of one rank this is always safe.  On groups of several ranks,
an exception that is not collective by construction (parflow raises InputError, SolveError and
WriteError on every rank of the communicator at once) may have left the group's other ranks
inside a collective: it is recorded, and the job is aborted rather than left to hang (restart
it with --restart FOLDER).  A signal (SIGINT / SIGTERM, relayed by mpirun) stops each group at
the end of its step with a checkpoint, like a single run; no new sample is started.

*Records.*  Each finished sample leaves ``FOLDER/.ensemble/sample_0007.json`` (its index,
seed, status, message, steps, wall and CPU seconds of its group's rank 0; written whole by a
rename); at the end world rank 0 writes the index ``FOLDER/ensemble.h5`` (``io.atomic_h5``: the scene, settings, rule,
and one row per sample), the statistics ``FOLDER/summary.h5`` (``post.ensemble``) and, for a
suspension or network ensemble, its sample table ``FOLDER/samples.json`` (:data:`SAMPLE_TABLES`).

The [ensemble] table (samples, ranks_per_sample) is ``scene.EnsembleOptions``, re-exported
here: the scene schema sits below the run.

*Restart* (``--restart FOLDER``): a sample whose file says complete, jammed or budget, or that
is recorded as failed, is skipped; one whose file says running or interrupted and holds a
checkpoint continues from it (the run file's restart: bit-identical to an uninterrupted run);
the others start afresh.  With ``retry`` (``--retry``) a sample that stopped ``jammed`` or
``failed`` is continued from its file's checkpoint instead (after a fix: the file then records
``retried_after``, the status and message it had), or started afresh if it has none.
"""
from __future__ import annotations

import json
import logging
import os
import re
import sys
import threading
import time

import h5py
import numpy as np

from .algebra.comm import idle_barrier, max_over, split_world, world
from .algebra.solvers import SolveError, collective_cleanup
from .checkpoint import check_checkpoint
from .errors import InputError, Terminated, collective
from .io import RunFile, WriteError, atomic_h5, atomic_json, check_output_path
from .post.ensemble import write_summary
from .post import network_across_ensembles, suspension_across_ensembles
from .protocol import hms
from .provenance import git_commit
from .run import Run
from .scene import EnsembleOptions, apply_settings, load_scene  # noqa: F401  ([ensemble])
from .state import STOPS

log = logging.getLogger("parflow")

INDEX_FORMAT = "parflow-ensemble-1"
SAMPLE_TABLE = "samples.json"       # the sample table of a suspension or network ensemble
# model -> the post module whose read_ensemble / export_samples write its sample table
SAMPLE_TABLES = {"suspension": suspension_across_ensembles, "network": network_across_ensembles}
SEED_RULE = ("seed_k = SeedSequence(seed, spawn_key=(k,)).generate_state(1, uint64)[0] >> 1 "
             "(numpy)")
DONE = ("complete", "jammed", "budget")          # a finished sample
FINAL = DONE + ("failed",)                       # skipped by a restart
RETRY = ("jammed", "failed")                     # continued by a restart with retry
COLLECTIVE_ERRORS = (InputError, SolveError, WriteError)   # raised on every rank at once


def sample_seed(seed: int, k: int) -> int:
    """Sample k's seed (the rule above): a function of the scene's seed and k only."""
    ss = np.random.SeedSequence(int(seed), spawn_key=(int(k),))
    return int(ss.generate_state(1, np.uint64)[0] >> np.uint64(1))


def sample_path(folder: str, k: int) -> str:
    return os.path.join(folder, f"sample_{k:04d}.h5")


def folder_of(output_path: str) -> str:
    """The ensemble's folder from an output path: ``out/run.h5`` -> ``out/run``."""
    return output_path[:-3] if output_path.endswith(".h5") else output_path


_SEED_LINE = re.compile(r"^[ \t]*seed[ \t]*=[^\n]*$")


SAMPLE_FIELD = "{sample}"


def sample_text(text: str, seed: int, source: str = "<scene>", sample: int | None = None) -> str:
    """The scene text with its top-level ``seed`` set to ``seed`` (the line replaced, or one
    added at the top); checked to parse to the same scene apart from the seed.  With
    ``sample``, every ``{sample}`` in the text (meant for ``model.configuration_file``: one
    prepared state per sample) is first replaced by the index as 4 digits (0007)."""
    if sample is not None:
        text = text.replace(SAMPLE_FIELD, f"{sample:04d}")
    lines = text.splitlines(keepends=True)
    end = next((i for i, ln in enumerate(lines) if ln.lstrip().startswith("[")), len(lines))
    hits = [i for i in range(end) if _SEED_LINE.match(lines[i].rstrip("\r\n"))]
    new = f"seed = {seed}    # sample seed (parflow.ensemble)\n"
    if len(hits) == 1:
        lines[hits[0]] = new
    elif not hits:
        lines.insert(0, new)
    out = "".join(lines)
    a, b = load_scene(text, source), None
    try:
        b = load_scene(out, source) if len(hits) <= 1 else None
    except InputError:
        pass
    if b is None or b["seed"] != seed or {**a, "seed": 0, "text": ""} != {**b, "seed": 0, "text": ""}:
        raise InputError(f"{source}: cannot set each sample's seed in the scene text: write the "
                         f"top-level seed as one line 'seed = N' before the first table")
    return out


# ---------------------------------------------------------------------------------------
# the folder: checks, index, records, restart plan (world rank 0)
# ---------------------------------------------------------------------------------------
def _records_dir(folder):
    return os.path.join(folder, ".ensemble")


def _claims_dir(folder):
    return os.path.join(folder, ".claims")


def read_records(folder: str) -> dict:
    """{sample: record} of the samples finished so far (the .ensemble/*.json records)."""
    out = {}
    d = _records_dir(folder)
    for name in sorted(os.listdir(d)) if os.path.isdir(d) else []:
        if name.startswith("sample_") and name.endswith(".json"):
            try:
                with open(os.path.join(d, name)) as fh:
                    rec = json.load(fh)
                out[int(rec["sample"])] = rec
            except (OSError, ValueError, KeyError):
                continue
    return out


def _record_path(folder: str, k: int) -> str:
    return os.path.join(_records_dir(folder), f"sample_{k:04d}.json")


def _write_record(folder: str, rec: dict) -> None:
    os.makedirs(_records_dir(folder), exist_ok=True)
    atomic_json(_record_path(folder, rec["sample"]), rec)


def read_index(folder: str) -> dict:
    """The ensemble index FOLDER/ensemble.h5: its attributes and per-sample rows."""
    path = os.path.join(folder, "ensemble.h5")
    if not os.path.isfile(path):
        raise InputError(f"{folder!r} is a directory, not a run file, and not an ensemble folder "
                         f"(no ensemble.h5 in it): --restart takes a run file or an ensemble folder")
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != INDEX_FORMAT:
                raise InputError(f"{path!r} is not a parflow ensemble index")
            attrs = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in f.attrs.items()}
            rows = {k: f[k][()] for k in f}
    except OSError as exc:
        raise InputError(f"cannot read the ensemble index {path!r}: {exc}") from None
    rows = {k: [x.decode() if isinstance(x, bytes) else x for x in v] for k, v in rows.items()}
    return dict(attrs=attrs, rows=rows)


def _write_index(folder: str, attrs: dict, samples: int, records: dict, plan=None) -> None:
    rows = []
    for k in range(samples):
        rec = records.get(k)
        if rec is None:
            rec = dict(sample=k, seed=sample_seed(attrs["seed"], k),
                       status="pending" if plan is None else plan[k], message="", steps=-1,
                       wall_seconds=float("nan"))
        rows.append(rec)
    with atomic_h5(os.path.join(folder, "ensemble.h5")) as f:
        for k, v in attrs.items():
            f.attrs[k] = v
        f.attrs["updated"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        f["sample"] = np.array([r["sample"] for r in rows], dtype=np.int64)
        f["seed"] = np.array([r["seed"] for r in rows], dtype=np.int64)
        for name in ("status", "message", "file"):
            vals = [str(r.get(name, "")) if name != "file" else os.path.basename(sample_path(folder, r["sample"]))
                    for r in rows]
            f.create_dataset(name, data=np.array(vals, dtype=object), dtype=h5py.string_dtype())
        f["steps"] = np.array([int(r.get("steps", -1)) for r in rows], dtype=np.int64)
        f["wall_seconds"] = np.array([float(r.get("wall_seconds", np.nan)) for r in rows])
        f["cpu_seconds"] = np.array([float(r.get("cpu_seconds", np.nan)) for r in rows])


def _sample_file_state(path: str, n_legs: int, model: str, retry: bool = False) -> str:
    """What a restart does with one sample file: 'skip' (finished), 'restart' (a checkpoint
    to continue from) or 'new'; with ``retry`` a file that stopped jammed or failed is
    continued (or started afresh) too."""
    if not os.path.exists(path):
        return "new"
    try:
        with RunFile(path) as run:
            status = str(run.attrs.get("status", ""))
            if status in FINAL and not (retry and status in RETRY):
                return "skip"
            if run.has_checkpoint:
                check_checkpoint(run.h5, path, n_legs, model)
                return "restart"
    except InputError as exc:
        log.warning("WARNING: %s: %s; the sample starts afresh", path, exc)
    return "new"


def prepare(folder: str, scene: dict, samples: int, rps: int, overwrite: bool,
            restart: bool, retry: bool = False) -> list:
    """Check the folder and write the index (world rank 0); the plan: one of 'new',
    'restart', 'skip' per sample (``retry``: the module's doc, *Restart*)."""
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise InputError(f"the ensemble's output {folder!r} is a file: an ensemble writes a "
                         f"folder (--output FOLDER)")
    index = os.path.join(folder, "ensemble.h5")
    if restart:
        recorded = read_records(folder)
        old = read_index(folder)
        for k, st in zip(old["rows"].get("sample", []), old["rows"].get("status", [])):
            if st == "failed" and k not in recorded:
                recorded[int(k)] = dict(sample=int(k), status="failed")
        n_legs, model = len(scene["protocol"]["leg"]), scene["model"]["name"]
        plan = []
        for k in range(samples):
            if recorded.get(k, {}).get("status") == "failed" and not retry:
                plan.append("skip")
            else:
                plan.append(_sample_file_state(sample_path(folder, k), n_legs, model, retry))
            if retry and plan[-1] != "skip" and k in recorded:
                os.remove(_record_path(folder, k))
    else:
        if os.path.exists(index) or any(n.startswith("sample_") for n in
                                        (os.listdir(folder) if os.path.isdir(folder) else [])):
            if not overwrite:
                raise InputError(f"{folder!r} holds an ensemble already: continue it with "
                                 f"--restart {folder}, pass --overwrite to replace it, or "
                                 f"--output another folder")
            for name in os.listdir(folder):
                if re.fullmatch(r"sample_\d+\.h5(\.tmp)?|ensemble\.h5|summary\.h5|samples\.json", name):
                    os.remove(os.path.join(folder, name))
            for d in (_records_dir(folder),):
                for name in os.listdir(d) if os.path.isdir(d) else []:
                    os.remove(os.path.join(d, name))
        check_output_path(index, True)
        plan = ["new"] * samples
    _check_sample_files(scene, samples, plan)
    claims = _claims_dir(folder)
    os.makedirs(claims, exist_ok=True)
    for name in os.listdir(claims):            # claims of an earlier job
        os.remove(os.path.join(claims, name))
    for k, p in enumerate(plan):
        if p == "skip":
            _claim(folder, k)
    attrs = dict(format=INDEX_FORMAT, scene=scene["text"],
                 scene_settings="\n".join(scene.get("settings", [])), samples=samples,
                 ranks_per_sample=rps, seed=scene["seed"], seed_rule=SEED_RULE,
                 model=scene["model"]["name"],
                 created=time.strftime("%Y-%m-%dT%H:%M:%S%z"))
    if restart:
        attrs["created"] = read_index(folder)["attrs"].get("created", attrs["created"])
    _write_index(folder, attrs, samples, read_records(folder) if restart else {}, plan)
    return plan


def _stopped_as(path: str) -> str:
    """'status: message' of a sample file that stopped jammed or failed ('' otherwise)."""
    with RunFile(path) as run:
        status = str(run.attrs.get("status", ""))
        return f"{status}: {run.attrs.get('message', '')}" if status in RETRY else ""


def _check_sample_files(scene: dict, samples: int, plan: list) -> None:
    """A ``model.configuration_file`` with ``{sample}``: refused before any sample runs if no
    sample that starts afresh has its file (a wrong path); if only some lack one (e.g. a
    state that did not relax when compressed), those samples fail with the model's message
    and are recorded as failed, like any failing sample, and the others run."""
    path = str(scene["model"].get("configuration_file", "") or "")
    if SAMPLE_FIELD not in path:
        return
    new = [k for k in range(samples) if plan[k] == "new"]
    missing = [k for k in new if not os.path.isfile(path.replace(SAMPLE_FIELD, f"{k:04d}"))]
    if new and len(missing) == len(new):
        raise InputError(f"model.configuration_file {path!r}: no sample has its file (first: "
                         f"{path.replace(SAMPLE_FIELD, f'{missing[0]:04d}')!r}); prepare one per "
                         f"sample (python -m parflow.prepare compress ENSEMBLE_FOLDER --out "
                         f"'...{SAMPLE_FIELD}.npz')")
    if missing:
        log.warning("WARNING: model.configuration_file %r: samples %s have no file and will "
                    "be recorded as failed", path, ", ".join(map(str, missing)))


def _claim(folder: str, k: int) -> bool:
    try:
        fd = os.open(os.path.join(_claims_dir(folder), f"{k:04d}"), os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return False
    os.close(fd)
    return True


def _next_sample(folder: str, samples: int, start: int) -> int:
    """Claim the lowest unclaimed sample index >= start; -1 when none is left."""
    for k in range(start, samples):
        if _claim(folder, k):
            return k
    return -1


# ---------------------------------------------------------------------------------------
# one sample, in its group
# ---------------------------------------------------------------------------------------
def _restart_scene_of(path: str) -> tuple:
    with RunFile(path) as run:
        return run.scene_text, run.settings


class _SampleFormatter(logging.Formatter):
    """"[parflow] sample k: ..." for a sample's lines; the job's own progress line (logged
    with ``ensemble_line``, from world rank 0's progress thread while its sample runs) as
    "[parflow] ..."."""

    def __init__(self, k: int):
        super().__init__("[parflow] %(message)s")
        self.k = k

    def format(self, record):
        line = super().format(record)
        if getattr(record, "ensemble_line", False):
            return line
        return line.replace("[parflow] ", f"[parflow] sample {self.k}: ", 1)


class sample_log:
    """While sample k runs: its group leader's log lines on stderr, each marked "sample k:".

    The job's log (setup_logging) has a handler on world rank 0 only, so the samples of the
    other groups would run silent; inside this context every group's leader prints its own
    sample's lines (restart, progress, end), world rank 0 included, and the ensemble's
    lines outside it stay world rank 0's alone."""

    def __init__(self, group, k: int, quiet: bool):
        self.on = group.getRank() == 0 and not quiet
        self.k, self.saved = k, None

    def __enter__(self):
        if self.on:
            self.saved = (list(log.handlers), log.level)
            h = logging.StreamHandler(sys.stderr)
            h.setFormatter(_SampleFormatter(self.k))
            log.handlers[:] = [h]
            log.setLevel(logging.INFO)
        return self

    def __exit__(self, *exc):
        if self.saved is not None:
            log.handlers[:], level = self.saved
            log.setLevel(level)
        return False


def run_sample(group, folder: str, k: int, mode: str, base: dict, cmdline, max_steps,
               quiet: bool) -> dict:
    """Run (or continue) sample k on the group's communicator; its record.  Exceptions of
    the sample are the caller's."""
    path = sample_path(folder, k)
    seed = sample_seed(base["seed"], k)
    attrs = dict(sample=k, sample_seed=seed)
    if mode == "restart":
        text, before = collective(group, _restart_scene_of, path)
        scene = apply_settings(load_scene(text, path), before)
        stopped = collective(group, _stopped_as, path)
        if stopped:                          # a retry (--retry): the file keeps why it stopped
            attrs["retried_after"] = stopped
    else:
        scene = apply_settings(load_scene(sample_text(base["text"], seed, base["source"], k),
                                          base["source"]), base["settings"])
        scene["output"]["path"] = path
        collective(group, check_output_path, path, True)
    t0, c0 = time.monotonic(), time.process_time()
    status = Run(scene, group, path, quiet=quiet, cmdline_options=cmdline,
                 restart=mode == "restart", max_steps=max_steps, file_attrs=attrs).execute()
    return dict(sample=k, seed=seed, status=status, message="", steps=-1,
                wall_seconds=time.monotonic() - t0, cpu_seconds=time.process_time() - c0)


def _from_file(rec: dict, path: str) -> dict:
    """The record completed from the sample file's own status, message and steps."""
    try:
        with RunFile(path) as run:
            a = run.attrs
        rec["message"] = rec["message"] or str(a.get("message", ""))
        rec["steps"] = int(a.get("steps", rec["steps"]))
    except (InputError, OSError, ValueError, TypeError):
        pass
    return rec


# ---------------------------------------------------------------------------------------
# the job
# ---------------------------------------------------------------------------------------
class _Progress(threading.Thread):
    """World rank 0's progress line: samples done / running / failed and an ETA."""

    def __init__(self, folder, samples, todo, seconds):
        super().__init__(daemon=True)
        self.folder, self.samples, self.todo, self.seconds = folder, samples, todo, seconds
        self.stop = threading.Event()
        self.t0 = time.monotonic()
        self.before = set(read_records(folder))

    def line(self) -> str:
        recs = read_records(self.folder)
        try:
            claimed = len(os.listdir(_claims_dir(self.folder)))
        except OSError:
            claimed = 0
        done = sum(r["status"] in DONE for r in recs.values())
        failed = sum(r["status"] == "failed" for r in recs.values())
        new = len(set(recs) - self.before)
        running = max(claimed - len(recs), 0)
        dt = time.monotonic() - self.t0
        eta = (self.todo - new) * dt / new if new else float("nan")
        return (f"ensemble: {done}/{self.samples} samples done, {running} running, "
                f"{failed} failed; ETA {hms(eta)}")

    def run(self):
        while not self.stop.wait(self.seconds):
            log.info("%s", self.line(), extra={"ensemble_line": True})


def run_ensemble(base: dict, folder: str, samples: int, rps: int, *, restart: bool,
                 overwrite: bool, cmdline: set, max_steps, quiet: bool, retry: bool = False) -> int:
    """Run the ensemble (collective on COMM_WORLD).  ``base``: the scene (``text``,
    ``seed``, ``source``, ``settings`` and the loaded scene as ``scene``).  Returns the exit
    status: 0 every sample finished, 1 one or more failed; raises KeyboardInterrupt /
    Terminated (collectively) when a signal stopped it."""
    w = world()
    git_commit()                  # read now, once: every sample records the code this job runs
    if w.getSize() % rps:
        raise InputError(f"ranks_per_sample = {rps} does not divide the job's {w.getSize()} "
                         f"ranks: run on a multiple of {rps} ranks")
    plan = collective(w, prepare, folder, base["scene"], samples, rps, overwrite, restart, retry)
    group, g, n_groups = split_world(rps)
    leader = group.getRank() == 0
    todo = sum(p != "skip" for p in plan)
    log.info("ensemble: %d samples (%d to run) on %d group(s) of %d rank(s) into %s; "
             "seed rule %s", samples, todo, n_groups, rps, folder, SEED_RULE)
    progress = None
    if w.getRank() == 0 and not quiet:
        progress = _Progress(folder, samples, todo, max(base["scene"]["output"]["progress_seconds"], 1.0))
        progress.start()
    stop_code = 0
    with STOPS.deferred():        # between samples a signal is taken here, not mid-write
        k = 0
        while True:
            if STOPS.pending:
                stop_code = max(stop_code, STOPS.pending)
                break
            k = _next_sample(folder, samples, 0) if leader else None
            k = group.tompi4py().bcast(k, root=0)
            if k < 0:
                break
            rec, stop = None, None
            try:
                with sample_log(group, k, quiet):
                    rec = run_sample(group, folder, k, plan[k], base, cmdline, max_steps, quiet)
            except (KeyboardInterrupt, Terminated) as exc:
                stop = exc
                rec = dict(sample=k, seed=sample_seed(base["seed"], k), status="interrupted",
                           message=f"{type(exc).__name__}: {exc}", steps=-1, wall_seconds=float("nan"))
            except Exception as exc:       # one sample's failure is recorded, not the job's
                rec = dict(sample=k, seed=sample_seed(base["seed"], k), status="failed",
                           message=f"{type(exc).__name__}: {exc}", steps=-1, wall_seconds=float("nan"))
                if group.getSize() > 1 and not isinstance(exc, COLLECTIVE_ERRORS):
                    _write_record(folder, _from_file(rec, sample_path(folder, k)))
                    print(f"parflow.shear: ensemble: sample {k} failed on one rank of its group "
                          f"({rec['message']}): the group's other ranks may be inside a "
                          f"collective; aborting (continue with --restart {folder})",
                          file=sys.stderr, flush=True)
                    w.tompi4py().Abort(1)
            if leader:
                rec = _from_file(rec, sample_path(folder, k))
                if rec["status"] != "interrupted":
                    _write_record(folder, rec)
                if rec["status"] == "failed":
                    log.info("ensemble: sample %d failed: %s", k, rec["message"])
            collective_cleanup(group, self_too=True)
            if stop is not None:
                stop_code = max(stop_code, 2 if isinstance(stop, Terminated) else 1)
                break
        # Waiting for the other groups, and while the summary is written, a signal is held
        # as during a step: taken at once it would abort the job from an idle rank and kill
        # the groups still inside a step before they wrote their checkpoints (measured: a
        # chain sample lost 293 steps that way).  Held, it stops the job here, with exit
        # 143 / 130, after every group has stopped at the end of its step.
        idle_barrier(w)
        stop_code = max_over(w, max(stop_code, STOPS.pending))
        if progress is not None:
            progress.stop.set()
        result = None
        if w.getRank() == 0:
            result = _finish(folder, base, samples, rps, stop_code)
        idle_barrier(w)
        result = w.tompi4py().bcast(result, root=0)
    if stop_code:
        exc = (Terminated if stop_code == 2 else KeyboardInterrupt)(
            f"ensemble stopped by a signal; continue with --restart {folder}")
        exc.mid_step, exc.collective = False, True
        raise exc
    return result


def _finish(folder: str, base: dict, samples: int, rps: int, stop_code: int) -> int:
    """World rank 0 at the end: the index, the summary, the closing lines; the exit status."""
    recs = read_records(folder)
    claims = _claims_dir(folder)
    for name in os.listdir(claims) if os.path.isdir(claims) else []:
        os.remove(os.path.join(claims, name))
    if os.path.isdir(claims):
        os.rmdir(claims)
    idx = read_index(folder)
    attrs = {k: v for k, v in idx["attrs"].items() if k != "updated"}
    _write_index(folder, attrs, samples, recs)
    counts = {}
    for r in recs.values():
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    unfinished = samples - len(recs)
    text = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    log.info("ensemble: %d samples: %s%s; index %s", samples, text or "none finished",
             f", {unfinished} not finished" if unfinished else "", os.path.join(folder, "ensemble.h5"))
    code = 0
    try:
        path = write_summary(folder)
        log.info("ensemble: summary %s", path)
    except Exception as exc:    # the samples are on disk: a summary that fails says so
        print(f"parflow.shear: ensemble: summary not written ({type(exc).__name__}: {exc}); "
              f"the sample files are in {folder}", file=sys.stderr)
        code = 1
    tables = SAMPLE_TABLES.get(base["scene"]["model"]["name"])
    if tables is not None:
        try:              # the sample table (docs/ensembles.md "Sample tables")
            table = os.path.join(folder, SAMPLE_TABLE)
            tables.export_samples(tables.read_ensemble(folder), table)
            log.info("ensemble: sample table %s", table)
        except Exception as exc:
            print(f"parflow.shear: ensemble: sample table not written ({type(exc).__name__}: "
                  f"{exc}); the sample files are in {folder}", file=sys.stderr)
            code = 1
    failed = sorted(k for k, r in recs.items() if r["status"] == "failed")
    if failed:
        first = recs[failed[0]]
        print(f"parflow.shear: ensemble: {len(failed)} of {samples} samples failed (sample "
              f"{failed[0]}: {first['message']}); the others ran on; statuses in "
              f"{os.path.join(folder, 'ensemble.h5')}", file=sys.stderr)
        code = 1
    return code

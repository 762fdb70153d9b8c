"""The models: one module each under ``parflow/models/``, keeping the contract of
``models/base.py`` (NAME, ENGINE, FLOW, PARAMS, FACTOR_REUSE, build, observables,
analyses(at), omega_min).  ``MODELS`` names them; ``get_model`` returns the module; a model
defined elsewhere (a user's module, a test) joins with ``register_model``.  Below: what a run
of each model needs in memory (``check_memory``: the scene check before anything is built)."""
import os
from importlib import import_module

from ..algebra.solvers import PARALLEL_FACTORS, resolve_parallel
from ..state import InputError
from .base import check_contract

MODELS = ["chain", "network", "suspension"]
_REGISTERED = {}                    # name -> module, for models registered at run time


def get_model(name: str):
    if name not in MODELS:
        raise InputError(f"model.name must be one of {list(MODELS)}, got {name!r}")
    if name in _REGISTERED:
        return _REGISTERED[name]
    return import_module(f".{name}", __name__)


def register_model(module) -> None:
    """Make the model ``module`` (any module or object keeping models/base.py's contract)
    available to scenes as ``model.name = module.NAME``."""
    check_contract(module)
    _REGISTERED[module.NAME] = module
    if module.NAME not in MODELS:
        MODELS.append(module.NAME)


def unregister_model(name: str) -> None:
    """Undo :func:`register_model` (the built-in models stay)."""
    if _REGISTERED.pop(name, None) is not None:
        MODELS.remove(name)


# --------------------------------------------------------------------------- memory
# What a run of each model holds in memory, per rank, measured on this code (peak RSS of
# short runs, /usr/bin/time): (unit of model.N, bytes per unit, bytes per rank on top,
# rows of N per unit (for the replicated / distributed choice), always replicated?)
#   chain: 0.92 kB per rod (N = 1e6: 1.0 GB, 3e6: 2.9 GB);
#   network: 3.4 kB per particle at N = 1e6 (docs/networks.md: 3.4 GB per rank, both ranks
#     holding the whole factor; Nc ~ 1.9 N rows);
#   suspension: 13 kB per disc at N = 65 536 (1.05 GB), 39 kB at 1e5 with analyses
#     (docs/suspensions.md); the contact step is replicated on every rank.
MEMORY = {
    "chain": dict(unit="rod", per_unit=0.92e3, per_rank=0.1e9, rows_per_unit=1.0, replicated=False),
    "network": dict(unit="particle", per_unit=3.4e3, per_rank=0.2e9, rows_per_unit=1.9,
                    replicated=False),
    "suspension": dict(unit="disc", per_unit=13e3, per_rank=0.2e9, rows_per_unit=2.0,
                       replicated=True),
}


def machine_memory() -> tuple[float, str]:
    """(bytes, where the number comes from): the machine's physical memory (MemTotal of
    /proc/meminfo, else sysconf), or the memory limit of this process's cgroup if smaller."""
    total, where = None, ""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemTotal:"):
                    total, where = float(line.split()[1]) * 1024, "MemTotal in /proc/meminfo"
                    break
    except OSError:
        pass
    if total is None:
        try:
            total = float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
            where = "physical pages (sysconf)"
        except (ValueError, OSError, AttributeError):
            return float("inf"), "unknown"
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(path) as fh:
                limit = float(fh.read().strip())
        except (OSError, ValueError):        # absent, or "max"
            continue
        if 0 < limit < total:
            total, where = limit, f"the cgroup limit {path}"
        break
    return total, where


def _bytes(x: float) -> str:
    for unit, scale in (("PB", 1e15), ("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if x >= scale:
            return f"{x / scale:.3g} {unit}"
    return f"{x / 1e6:.2g} MB"


def memory_needed(name: str, n: int, n_ranks: int = 1, ranks_here: int | None = None,
                  parallel: str = "auto") -> float:
    """Bytes that a run of model ``name`` with model.N = ``n`` on ``n_ranks`` ranks needs on
    one machine holding ``ranks_here`` of them (default: all): each rank holds the whole system
    when it is replicated (one rank; "replicated"/"redundant"; "auto" below
    solvers.AUTO_REPLICATED_MAX_NC rows), else the ranks share the distributed part."""
    m = MEMORY[name]
    here = n_ranks if ranks_here is None else ranks_here
    rows = min(float(n) * m["rows_per_unit"], 2.0 ** 62)
    if parallel not in PARALLEL_FACTORS:
        parallel = "auto"
    strategy = "replicated" if m["replicated"] else resolve_parallel(parallel, int(rows), n_ranks)
    whole = m["per_unit"] * float(n)
    if strategy == "threads":            # the whole system on rank 0, the others idle
        return here * m["per_rank"] + whole
    if strategy in ("replicated", "redundant"):
        return here * (m["per_rank"] + whole)
    return here * m["per_rank"] + whole * here / n_ranks


def check_memory(name: str, params: dict, n_ranks: int = 1, ranks_here: int | None = None,
                 parallel: str = "auto", available: tuple[float, str] | None = None) -> None:
    """InputError if the run would need more memory than the machine has (before anything
    is allocated: model.N up to 2^70 and beyond is only multiplied here)."""
    if name not in MEMORY or not isinstance(params.get("N"), int):
        return
    n = params["N"]
    have, where = available or machine_memory()
    need = memory_needed(name, n, n_ranks, ranks_here, parallel)
    if need <= have:
        return
    m = MEMORY[name]
    here = n_ranks if ranks_here is None else ranks_here
    fit = 0
    for k in range(64, -1, -1):                      # the largest N that fits (bisection)
        if memory_needed(name, fit + 2 ** k, n_ranks, ranks_here, parallel) <= have:
            fit += 2 ** k
    ranks = f" on each of {here} ranks" if here > 1 else ""
    hint = (f"choose model.N <= {fit:,} (for {n_ranks} rank{'s' if n_ranks > 1 else ''}, "
            f"{here} on this machine)" if fit >= 1
            else "this machine cannot hold even the program on that many ranks")
    shown = f"{n:,}" if n < 10 ** 15 else f"{n:.4g}"
    raise InputError(f"model.N = {shown}: a {name} of that size would need about {_bytes(need)} of "
                     f"memory (~{m['per_unit'] / 1e3:.3g} kB per {m['unit']}{ranks}), more than the "
                     f"{_bytes(have)} this machine has ({where}); {hint}")

# Run-time environment for parflow.  The single place where it is defined:
# sourced by scripts/setup.sh, the Makefile recipes and .ci/run.
#
#   . scripts/env.sh        # then: .venv/bin/python ..., mpirun -n 2 ...
#
# POSIX sh, safe under `set -eu`.  Values the user already exported win, except that
# PETSC_DIR / SLEPC_DIR are replaced when they do not hold petsc4py / slepc4py.

# Where Debian puts PETSc and SLEPc.  Overridable (tests point them at an empty folder to
# play a machine where nothing is installed yet).
_parflow_petsc_root="${PARFLOW_PETSC_ROOT:-/usr/lib/petscdir}"
_parflow_slepc_root="${PARFLOW_SLEPC_ROOT:-/usr/lib/slepcdir}"

# Newest directory matching a glob pattern (version-aware sort), or nothing.  Must succeed
# under `set -euo pipefail` when nothing matches (a fresh machine): no `ls` of a missing
# glob, and every command in the pipeline exits 0.
_parflow_newest() {
    # shellcheck disable=SC2086  # the pattern must glob
    for _parflow_d in $1; do
        if [ -d "$_parflow_d" ]; then printf '%s\n' "$_parflow_d"; fi
    done | sort -V | tail -n 1
}

# Debian ships petsc4py/slepc4py under $PETSC_DIR/lib/python3/dist-packages and finds
# them through a .pth file that reads PETSC_DIR (falling back to the /usr/lib/petsc
# alternatives symlink, which is not always present).  So PETSC_DIR must be set.
if [ -z "${PETSC_DIR:-}" ] || [ ! -d "${PETSC_DIR}/lib/python3/dist-packages/petsc4py" ]; then
    PETSC_DIR=$(_parflow_newest "${_parflow_petsc_root}/petsc*/*-real")
fi
if [ -z "${SLEPC_DIR:-}" ] || [ ! -d "${SLEPC_DIR}/lib/python3/dist-packages/slepc4py" ]; then
    SLEPC_DIR=""
    if [ -n "${PETSC_DIR:-}" ]; then
        # Prefer the SLEPc that matches the PETSc version and arch (petsc3.18/x -> slepc3.18/x).
        _parflow_v=$(basename "$(dirname "${PETSC_DIR}")" | sed 's/^petsc//')
        _parflow_a=$(basename "${PETSC_DIR}")
        if [ -d "${_parflow_slepc_root}/slepc${_parflow_v}/${_parflow_a}" ]; then
            SLEPC_DIR="${_parflow_slepc_root}/slepc${_parflow_v}/${_parflow_a}"
        fi
        unset _parflow_v _parflow_a
    fi
    if [ -z "${SLEPC_DIR}" ]; then
        SLEPC_DIR=$(_parflow_newest "${_parflow_slepc_root}/slepc*/*-real")
    fi
fi
unset -f _parflow_newest
unset _parflow_petsc_root _parflow_slepc_root
# Empty on a machine where PETSc is not installed yet (scripts/setup.sh installs it
# and sources this file again).
if [ -n "${PETSC_DIR:-}" ]; then export PETSC_DIR; else unset PETSC_DIR; fi
if [ -n "${SLEPC_DIR:-}" ]; then export SLEPC_DIR; else unset SLEPC_DIR; fi

# Open MPI: allow root (containers, CI) and more ranks than cores.
export OMPI_ALLOW_RUN_AS_ROOT=1
export OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
export OMPI_MCA_rmaps_base_oversubscribe=1
# Yield the core while waiting in MPI: keeps 2 ranks usable when another process shares the cores.
export OMPI_MCA_mpi_yield_when_idle="${OMPI_MCA_mpi_yield_when_idle:-1}"

# One thread per MPI rank: threaded BLAS under mpirun oversubscribes the cores.
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"

# The same arithmetic on every x86-64 machine (docs/conventions.md "The same numbers on every
# machine"): OpenBLAS (under CHOLMOD and numpy) and numpy pick their kernels by the CPU, and
# another kernel sums in another order, so the same scene differed at round-off between an
# AVX-512 machine and an AMD one -- which a chain near its turn grows to 1e-3.  Pin OpenBLAS
# to its AVX2 "Haswell" kernels (what it picks for AMD Zen, too) and, where the CPU has
# AVX-512, switch off numpy's AVX-512 paths (only the features the CPU has: naming one it
# lacks makes numpy warn at import).
if [ "$(uname -m 2>/dev/null)" = x86_64 ] && grep -qw avx2 /proc/cpuinfo 2>/dev/null; then
    export OPENBLAS_CORETYPE="${OPENBLAS_CORETYPE:-Haswell}"
    if [ -z "${NPY_DISABLE_CPU_FEATURES+x}" ] && grep -qw avx512f /proc/cpuinfo; then
        _parflow_npy_off=$(/usr/bin/python3 -c 'from numpy.core._multiarray_umath import __cpu_features__ as f, __cpu_dispatch__ as d
print(" ".join(k for k in d if k.startswith("AVX512") and f.get(k)))' 2>/dev/null || true)
        if [ -n "${_parflow_npy_off}" ]; then export NPY_DISABLE_CPU_FEATURES="${_parflow_npy_off}"; fi
        unset _parflow_npy_off
    fi
fi

# Ignore ~/.local/lib/python3.X: a pip-installed numpy 2 there would shadow Debian's
# numpy 1.24, which petsc4py/h5py/scipy are built against.
export PYTHONNOUSERSITE=1

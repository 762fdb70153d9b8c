#!/usr/bin/env bash
# One-command setup for parflow (Debian 12 or newer):
#   1. apt-get install PETSc/SLEPc/MPI/h5py/scipy/... for Debian's /usr/bin/python3
#      (skipped when they already import, so a second run takes a few seconds);
#      pytest-xdist likewise, but optional (a failed install only warns);
#   2. a venv .venv with --system-site-packages on top of /usr/bin/python3;
#   3. parflow installed editable into it, without dependencies (pip must never
#      build PETSc or pull numpy 2 from PyPI);
#   4. sanity checks, then the stamp file .venv/.parflow-setup-stamp for make.
#
# Usage: bash scripts/setup.sh      (or: make setup)
#        PARFLOW_FORCE_APT=1 bash scripts/setup.sh   to run the apt step even if not needed
#        PARFLOW_SETUP_DRY_RUN=1 bash scripts/setup.sh   print what the apt step would run and
#                                                         stop there (exit 0; nothing installed)
set -euo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."
REPO=$(pwd)
SYS_PY=/usr/bin/python3
VENV="$REPO/.venv"
STAMP="$VENV/.parflow-setup-stamp"

APT_PACKAGES=(
    python3-petsc4py python3-slepc4py python3-mpi4py python3-h5py-mpi
    python3-numpy python3-scipy python3-matplotlib python3-pytest
    python3-venv python3-setuptools python3-wheel python3-numba
    openmpi-bin make
)
# Not required: runs the serial test session on every core (make test falls back to one
# process without it).  Installed by the apt step when missing; a failure there only warns.
APT_OPTIONAL=(python3-pytest-xdist)

log() { printf '[setup] %s\n' "$*"; }
die() { printf '[setup] ERROR: %s\n' "$*" >&2; exit 1; }

# shellcheck source=scripts/env.sh
. "$REPO/scripts/env.sh"

# Everything parflow needs from the system, checked with Debian's python.
system_ready() {
    [ -x "$SYS_PY" ] || return 1
    command -v mpirun >/dev/null 2>&1 || return 1
    command -v make >/dev/null 2>&1 || return 1
    [ -n "${PETSC_DIR:-}" ] && [ -n "${SLEPC_DIR:-}" ] || return 1
    # H5PY_ALWAYS_USE_MPI makes Debian's h5py load its MPI build outside mpirun.
    H5PY_ALWAYS_USE_MPI=1 "$SYS_PY" - >/dev/null 2>&1 <<'EOF'
import ensurepip, venv, setuptools, wheel
import numpy, scipy, matplotlib, pytest, mpi4py, numba
import petsc4py, slepc4py
import h5py
assert h5py.get_config().mpi, "h5py without MPI"
EOF
}

# --- 1. system packages ------------------------------------------------------------
if [ "${PARFLOW_FORCE_APT:-0}" != 1 ] && system_ready; then
    log "system packages present (PETSC_DIR=$PETSC_DIR), skipping apt"
else
    log "installing system packages with apt: ${APT_PACKAGES[*]}"
    if [ "${PARFLOW_SETUP_DRY_RUN:-0}" = 1 ]; then
        log "dry run: would run apt-get update && apt-get install -y ${APT_PACKAGES[*]}"
        exit 0
    fi
    SUDO=()
    if [ "$(id -u)" -ne 0 ]; then
        command -v sudo >/dev/null 2>&1 || die "not root and no sudo: install ${APT_PACKAGES[*]} by hand"
        SUDO=(sudo)
    fi
    export DEBIAN_FRONTEND=noninteractive
    "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get update
    "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y "${APT_PACKAGES[@]}"
    # PETSC_DIR/SLEPC_DIR exist only now.
    unset PETSC_DIR SLEPC_DIR
    . "$REPO/scripts/env.sh"
    if ! system_ready; then
        H5PY_ALWAYS_USE_MPI=1 "$SYS_PY" -c 'import petsc4py, slepc4py, mpi4py, h5py, scipy, matplotlib, pytest' || true
        die "system packages still not importable after apt (PETSC_DIR=${PETSC_DIR:-unset}, SLEPC_DIR=${SLEPC_DIR:-unset})"
    fi
fi

# optional packages: one apt attempt when missing, never fatal
if ! "$SYS_PY" -c 'import xdist' >/dev/null 2>&1; then
    if [ "${PARFLOW_SETUP_DRY_RUN:-0}" = 1 ]; then
        log "dry run: would run apt-get install -y ${APT_OPTIONAL[*]}"
    else
        log "installing optional packages with apt: ${APT_OPTIONAL[*]}"
        SUDO=()
        [ "$(id -u)" -eq 0 ] || SUDO=(sudo)
        apt_optional() { "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get "$@" >/dev/null 2>&1; }
        if ! apt_optional install -y "${APT_OPTIONAL[@]}" &&
           ! { apt_optional update && apt_optional install -y "${APT_OPTIONAL[@]}"; }; then
            log "warning: could not install ${APT_OPTIONAL[*]}: make test runs its serial part in one process"
        fi
    fi
fi

# --- 2. venv -------------------------------------------------------------------------
venv_ok() {
    [ -x "$VENV/bin/python" ] || return 1
    grep -qs '^include-system-site-packages *= *true' "$VENV/pyvenv.cfg" || return 1
    # The venv must sit on the Debian interpreter (same version as the system packages).
    [ "$("$VENV/bin/python" -c 'import sys; print(sys.base_prefix)' 2>/dev/null)" = \
      "$("$SYS_PY" -c 'import sys; print(sys.base_prefix)')" ] || return 1
}
if venv_ok; then
    log "venv $VENV present"
else
    if [ -e "$VENV" ]; then
        log "removing unusable venv $VENV"
        rm -rf "$VENV"
    fi
    log "creating venv $VENV (--system-site-packages on $SYS_PY)"
    "$SYS_PY" -m venv --system-site-packages "$VENV"
fi

# --- 3. parflow, editable, no dependencies ------------------------------------------
log "pip install --no-deps --no-build-isolation -e ."
PIP_DISABLE_PIP_VERSION_CHECK=1 "$VENV/bin/python" -m pip install --quiet \
    --no-deps --no-build-isolation --no-index -e "$REPO"

# --- 4. checks (from / so that parflow is found through the install, not the cwd) ----
(cd / && PARFLOW_REPO="$REPO" "$VENV/bin/python" -) <<'EOF'
import sys
import numpy
if not numpy.__version__.startswith("1.") or not numpy.__file__.startswith("/usr/lib/python3/"):
    sys.exit(f"[setup] ERROR: venv numpy is {numpy.__version__} from {numpy.__file__}; "
             "expected Debian's 1.x from /usr/lib/python3/dist-packages (remove the other one)")
import petsc4py
petsc4py.init(sys.argv[:1])
from petsc4py import PETSc
import slepc4py
slepc4py.init(sys.argv[:1])
from slepc4py import SLEPc
import mpi4py, scipy, h5py, matplotlib, pytest
import importlib.util, os
spec = importlib.util.find_spec("parflow")   # locate only: do not run package code here
locs = [os.path.realpath(d) for d in (spec.submodule_search_locations or [])] if spec else []
if os.path.realpath(os.path.join(os.environ["PARFLOW_REPO"], "parflow")) not in locs:
    sys.exit(f"[setup] ERROR: parflow is not the editable install of this checkout: {spec}")
v = lambda t: ".".join(map(str, t))
print(f"[setup] ok: python {v(sys.version_info[:3])}, numpy {numpy.__version__}, "
      f"scipy {scipy.__version__}, PETSc {v(PETSc.Sys.getVersion())}, "
      f"SLEPc {v(SLEPc.Sys.getVersion())}, mpi4py {mpi4py.__version__}, h5py {h5py.__version__}")
EOF

touch "$STAMP"
log "done. Next: make test  |  make run"

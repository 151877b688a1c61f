#!/usr/bin/env bash
# One-command set-up on Debian 12: system packages (FEniCSx stack, MPI, OpenBLAS) and the .venv.
# Idempotent: a second run checks, installs nothing new and finishes in seconds.
set -euo pipefail
cd "$(dirname "$0")/.."

DEB_PACKAGES=(
  python3-dolfinx python3-gmsh python3-mpi4py python3-petsc4py python3-h5py python3-meshio
  python3-venv python3-pip python3-scipy python3-matplotlib python3-tqdm
  openmpi-bin libopenblas0 make git
  g++ python3-dev  # the C++ compiler and headers learn/aot.py's AOTInductor packages are built with (FFCx's JIT too)
)
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi

missing=()
for p in "${DEB_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "[setup] installing Debian packages: ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
else
  echo "[setup] Debian packages present"
fi

# The venv must sit on Debian's python3 so it sees dolfinx, gmsh, petsc4py, mpi4py, h5py and numpy 1.24.
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv on /usr/bin/python3 with system site packages"
  /usr/bin/python3 -m venv --system-site-packages .venv
fi
# Pin Debian's numpy: a pip numpy 2 breaks dolfinx's compiled modules.
NUMPY_VERSION=$(/usr/bin/python3 -c "import numpy; print(numpy.__version__)")
echo "numpy==${NUMPY_VERSION}" > .venv/constraints.txt

stamp=.venv/.installed-$(sha1sum pyproject.toml | cut -c1-12)
if [ ! -f "$stamp" ]; then
  echo "[setup] installing the project (editable) with torch (CPU), hydra and dev tools"
  .venv/bin/python -m pip install -q --disable-pip-version-check -c .venv/constraints.txt -e ".[learn,dev]"
  rm -f .venv/.installed-*
  touch "$stamp"
else
  echo "[setup] Python environment up to date"
fi
.venv/bin/python - <<'PY'
import dolfinx, gmsh, h5py, numpy, torch, hydra
print(f"[setup] ok: dolfinx {dolfinx.__version__}, gmsh {gmsh.__version__}, numpy {numpy.__version__}, "
      f"h5py {h5py.__version__}, torch {torch.__version__}, hydra {hydra.__version__}")
PY

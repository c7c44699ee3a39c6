#!/usr/bin/env bash
# Set up everything mono-map needs on a fresh machine; idempotent and quick when done already.
#   - Debian packages (when root): libusb-1.0-0 (open3d needs it), octomap-tools (OctoMap's C++ tools), gcc when
#     there is no C compiler (cc): pip install builds the C kernels of mono_map/csrc/ with it (without one,
#     mono-map runs its numpy paths: the same results, slower)
#   - a virtualenv (.venv, or $MONO_MAP_VENV) with torch 2.13.0 and mono-map installed in editable mode
#     with its test extras. torch comes from whatever index pip is configured with: a machine whose pip
#     finds a CPU wheel gets that (2.13.0+cpu on the project's machines); from plain PyPI on Linux x86-64
#     it is the default CUDA build, which is what a machine with an NVIDIA GPU wants. For a CPU-only
#     build anywhere, run with PIP_INDEX_URL=https://download.pytorch.org/whl/cpu (PyTorch's CPU index).
# Source it or run it; afterwards "$VENV/bin/mono-map" works.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${MONO_MAP_VENV:-$REPO/.venv}"
PY="${PYTHON:-python3}"

need_apt=()
for pkg in libusb-1.0-0 octomap-tools; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
done
command -v "${CC:-cc}" >/dev/null 2>&1 || need_apt+=(gcc)
if [ ${#need_apt[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then
    echo "setup: installing Debian packages: ${need_apt[*]}" >&2
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need_apt[@]}") >&2
  else
    echo "setup: warning: missing Debian packages ${need_apt[*]} (run as root or install them; open3d needs libusb-1.0-0)" >&2
  fi
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating virtualenv $VENV" >&2
  "$PY" -m venv "$VENV"
fi
stamp="$VENV/.mono-map-setup"
want="$(cat "$REPO/pyproject.toml" "$REPO/setup.py" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  log="$VENV/setup.log"
  echo "setup: installing Python packages into $VENV (first time takes a few minutes; log: $log)" >&2
  if ! {
    "$VENV/bin/python" -m pip install --upgrade pip &&
    # torch first, pinned: with it installed, "torch>=2.1" in pyproject.toml pulls nothing more.
    "$VENV/bin/python" -m pip install "torch==2.13.0" &&
    "$VENV/bin/python" -m pip install -e "$REPO[test]"
  } >"$log" 2>&1; then
    tail -n 30 "$log" >&2
    echo "setup: pip install failed (full log: $log)" >&2
    exit 1
  fi
  echo "$want" > "$stamp"
fi

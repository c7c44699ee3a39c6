#!/usr/bin/env bash
# The README's main command: set up, then run mono-map's main job end to end on the embedded default
# (synthetic sequence 00, its first 500 frames, and the shipped binary model). Extra arguments go to
# `mono-map demo` (e.g. --frames all for the full 4541-frame sequence).
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$REPO/tools/setup_env.sh"
cd "$REPO"
exec "${MONO_MAP_VENV:-$REPO/.venv}/bin/mono-map" demo "$@"

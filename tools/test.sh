#!/usr/bin/env bash
# The README's test command: set up, then run the test suite. Extra arguments go to pytest.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$REPO/tools/setup_env.sh"
cd "$REPO"
exec "${MONO_MAP_VENV:-$REPO/.venv}/bin/python" -m pytest -q "$@"

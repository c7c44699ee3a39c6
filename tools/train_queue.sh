#!/usr/bin/env bash
# Train the model-v2 comparison runs one after another, each resumable from its last.pt
# (~/.cache/mono-map/train/v2-NAME/). Run it from a separate git worktree so edits cannot change a
# running job; stop it any time and start it again to resume. Logs: ~/.cache/mono-map/logs/.
#   bash tools/train_queue.sh [NAME ...]      (default: every mono_map/depth/configs/v2/*.toml)
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${MONO_MAP_VENV:-$REPO/.venv}/bin/python"
LOGS="$HOME/.cache/mono-map/logs"
mkdir -p "$LOGS"
names=("$@")
if [ ${#names[@]} -eq 0 ]; then
  for f in "$REPO"/mono_map/depth/configs/v2/*.toml; do names+=("$(basename "$f" .toml)"); done
fi
for n in "${names[@]}"; do
  cfg="$REPO/mono_map/depth/configs/v2/$n.toml"
  [ -f "$cfg" ] || { echo "train_queue: $cfg: no such config" >&2; exit 2; }
  if [ -f "$HOME/.cache/mono-map/train/v2-$n/final.pt" ]; then echo "train_queue: v2-$n done"; continue; fi
  echo "train_queue: $(date -u +%H:%M:%S) training v2-$n (log $LOGS/train-v2-$n.log)"
  (cd "$REPO" && PYTHONPATH="$REPO" "$PY" -m mono_map train --config "$cfg" >>"$LOGS/train-v2-$n.log" 2>&1)
done

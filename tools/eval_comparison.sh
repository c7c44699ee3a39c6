#!/usr/bin/env bash
# Evaluate every finished model-v2 comparison run (~/.cache/mono-map/train/v2-*/final.pt, trained by
# tools/train_queue.sh) side by side: one eval-depth table per data set, every run a row.
#   bash tools/eval_comparison.sh [RUN ...]        (default: every v2-* run with a final.pt)
# Data sets: sequence 00 frames 0:500:10 against LiDAR (the held-out town), the validation town val09,
# training town t07_0a (the fit on training frames) and the real KITTI object frames in ../shared.
# Output: ~/.cache/mono-map/eval/v2cmp/{seq00,val09,t07,real}/ (JSON, Markdown, PNGs) and logs beside.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${MONO_MAP_VENV:-$REPO/.venv}/bin/python"
TRAIN="$HOME/.cache/mono-map/train"
OUT="${MONO_MAP_EVAL:-$HOME/.cache/mono-map/eval}/v2cmp"
DATA="${MONO_MAP_DATA:-$HOME/.cache/mono-map/data/kitti}"
SHARED="${MONO_MAP_SHARED:-$REPO/../shared}"
runs=("$@")
if [ ${#runs[@]} -eq 0 ]; then
  for f in "$TRAIN"/v2-*/final.pt; do [ -f "$f" ] && runs+=("$(basename "$(dirname "$f")")"); done
fi
[ ${#runs[@]} -gt 0 ] || { echo "eval_comparison: no finished v2 runs under $TRAIN" >&2; exit 2; }
models=()
for r in "${runs[@]}"; do
  f="$TRAIN/$r/final.pt"
  [ -f "$f" ] || { echo "eval_comparison: $f: no such checkpoint" >&2; exit 2; }
  models+=(--model "$f")
done
mkdir -p "$OUT"
echo "eval_comparison: ${runs[*]} -> $OUT" >&2
cd "$REPO"
run() { local name=$1; shift; echo "  $name ..." >&2; PYTHONPATH="$REPO" "$PY" -m mono_map eval-depth "$@" "${models[@]}" \
          --out "$OUT/$name" --threads 1 > "$OUT/$name.log" 2>&1 || { echo "eval_comparison: $name failed, see $OUT/$name.log" >&2; exit 1; }; }
run seq00 --seq 00 --data-root "$DATA" --frames 0:500:10
run val09 --trainset-town val09 --frames 0:250:10
run t07 --trainset-town t07_0a --frames 0:500:20
run real --kitti-object "$SHARED/kitti_real/object/training"
echo "eval_comparison: done; tables in $OUT/*/depth_*.md" >&2

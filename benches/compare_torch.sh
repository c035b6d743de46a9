#!/usr/bin/env bash
# Alternates the crate's training step (benches/train_step.rs) with its PyTorch twin
# (benches/torch/train_step.py) on the same cores and prints each run and the medians.
#
#   python3 -m venv venv && venv/bin/pip install torch numpy
#   benches/compare_torch.sh [PYTHON] [PAIRS] [MODELS...]
#
# PYTHON defaults to venv/bin/python, PAIRS to 4, MODELS to "nerf occupancy" (any of the
# bench's models: nerf, occupancy, dvr, hash_grid, onet_points, onet_voxels, onet_image).
# Both sides use every core (candle's CPU pool; torch.set_num_threads(os.cpu_count())) and
# the system allocator. The summary line gives each side's parameter count where its JSON
# line has one (they should be equal). Extra flags for the PyTorch side (e.g. --compile)
# go in TORCH_FLAGS: TORCH_FLAGS=--compile benches/compare_torch.sh venv/bin/python 3 onet_points
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${1:-venv/bin/python}
PAIRS=${2:-4}
shift $(( $# > 2 ? 2 : $# )) || true
MODELS=${*:-nerf occupancy}
cargo build --release --bench train_step >/dev/null 2>&1
BIN=$(cargo bench --bench train_step --no-run --message-format=json 2>/dev/null \
  | python3 -c 'import json,sys
for l in sys.stdin:
    m = json.loads(l)
    if m.get("reason") == "compiler-artifact" and m["target"]["name"] == "train_step" and m.get("executable"):
        print(m["executable"])')
for model in $MODELS; do
  out=$(mktemp)
  for _ in $(seq "$PAIRS"); do
    "$BIN" --model "$model" --steps 20 --phases | tee -a "$out"
    "$PY" benches/torch/train_step.py --model "$model" --steps 20 --phases ${TORCH_FLAGS:-} | tee -a "$out"
  done
  python3 - "$out" "$model" <<'PY'
import json, statistics, sys
rows = [json.loads(l) for l in open(sys.argv[1])]
med = lambda impl, key: statistics.median(r[key] for r in rows if r["impl"].startswith(impl))
c, t = med("candle", "median_s"), med("pytorch", "median_s")
print(f"{sys.argv[2]}: candle {c:.4f} s/step, pytorch {t:.4f} s/step, pytorch/candle = {t / c:.2f}"
      f" (forward {med('candle', 'forward_s'):.4f} vs {med('pytorch', 'forward_s'):.4f},"
      f" backward {med('candle', 'backward_s'):.4f} vs {med('pytorch', 'backward_s'):.4f})"
      + "".join(f", {impl} params {p}" for impl in ("candle", "pytorch")
                for p in {r["params"] for r in rows if r["impl"].startswith(impl) and "params" in r}))
PY
  rm -f "$out"
done

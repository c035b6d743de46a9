#!/usr/bin/env bash
# Every GPU check and benchmark of the `cuda` feature in one run, from binaries built
# beforehand on any machine (scripts/cuda-toolchain.sh, then scripts/gpu-build.sh), so
# that a short lease of a GPU machine builds nothing:
#
#     scripts/gpu-check.sh [BIN_DIR] [OUT_DIR]     # defaults: .gpu, ${OUT:-gpu-out}
#
# Writes to OUT_DIR (eight files, three more for the 400 × 400 run): summary.txt (nvidia-smi, timings, medians), tests.log (tests/cuda.rs with the CUDA
# kernels), tests_reference.log (the same with NEURAL_FIELDS_CUDA_KERNELS=0: the
# candle-op reference paths on CUDA against the CPU kernels), bench.jsonl (training steps:
# the crate with its CUDA kernels, the crate's candle-op fallback, PyTorch CUDA eager and
# torch.compile, alternated; bench.err), nerf.log, nerf_metrics.json and nerf_curve.csv (the NeRF
# example's time-to-PSNR run on the GPU; nerf400.* the same at 400 × 400). Needs python3 with torch for the PyTorch rows.
set -u
BIN=${1:-.gpu}
OUT=${2:-${OUT:-gpu-out}}
PAIRS=${PAIRS:-3}
NERF_SECONDS=${NERF_SECONDS:-90}
# Rays per step of the NeRF example's runs on the committed dataset (the 400 × 400 run
# takes the default, 1024, only).
NERF_RAYS=${NERF_RAYS:-1024}
# PHASES=0 times whole steps without the synchronisations between forward, backward and
# update that --phases adds (as a training loop runs); MODELS picks the benched steps
# (MODELS= with nothing skips the benches).
PHASES=${PHASES:-1}
MODELS=${MODELS-nerf nerf_hash hash_grid}
# The models also timed under torch.compile (its compilation takes a minute or more).
COMPILE_MODELS=${COMPILE_MODELS-$MODELS}
phases=--phases; [ "$PHASES" = 0 ] && phases=
mkdir -p "$OUT"
cd "$(dirname "$0")/.."
# Unpack the binaries that scripts/gpu-build.sh compressed.
if ls "$BIN"/*.xz > /dev/null 2>&1; then
  python3 - "$BIN" /tmp/nf-gpu-bin <<'PY'
import lzma, os, shutil, sys
src, dst = sys.argv[1], sys.argv[2]
os.makedirs(dst, exist_ok=True)
for f in os.listdir(src):
    if f.endswith(".xz"):
        with lzma.open(os.path.join(src, f)) as i, open(os.path.join(dst, f[:-3]), "wb") as o:
            shutil.copyfileobj(i, o)
        os.chmod(os.path.join(dst, f[:-3]), 0o755)
PY
  BIN=/tmp/nf-gpu-bin
fi

# The driver's libcuda.so.1 and CUDA 13's cuBLAS, cuRAND and NVRTC, wherever installed.
libs=$(find /usr/local /usr/lib /usr/lib64 /opt -xdev \( -name 'libcuda.so.1' -o \
  -name 'libcublas.so.13' -o -name 'libcublasLt.so.13' -o -name 'libcurand.so.10' -o \
  -name 'libnvrtc.so.13' -o -name 'libcudart.so.13' \) 2>/dev/null | xargs -r -n1 dirname | sort -u | tr '\n' ':')
export LD_LIBRARY_PATH="${libs}${LD_LIBRARY_PATH:-}"
{ nvidia-smi -L; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; \
  echo "LD_LIBRARY_PATH=$LD_LIBRARY_PATH"; nproc; } > "$OUT/summary.txt" 2>&1

start=$(date +%s)
stamp() { echo "[$(( $(date +%s) - start )) s] $*" | tee -a "$OUT/summary.txt"; }

stamp "tests with the CUDA kernels"
timeout 240 "$BIN/cuda" --test-threads 1 --nocapture > "$OUT/tests.log" 2>&1
stamp "rc=$? $(grep -E '^test result' "$OUT/tests.log" | tail -1)"
stamp "tests with the reference paths on CUDA"
NEURAL_FIELDS_CUDA_KERNELS=0 timeout 180 "$BIN/cuda" --test-threads 1 --nocapture \
  > "$OUT/tests_reference.log" 2>&1
stamp "rc=$? $(grep -E '^test result' "$OUT/tests_reference.log" | tail -1)"

stamp "training steps, alternated"
for model in $MODELS; do
  for _ in $(seq "$PAIRS"); do
    timeout 60 "$BIN/train_step" --model "$model" --steps 20 --device cuda $phases
    # The hash grid's candle-op fallback takes seconds per step: 2 steps after 1.
    fallback_steps=20
    case $model in hash_grid|nerf_hash) fallback_steps="2 --warmup 1";; esac
    NEURAL_FIELDS_CUDA_KERNELS=0 timeout 60 "$BIN/train_step" --model "$model" \
      --steps $fallback_steps --device cuda $phases
    timeout 60 python3 benches/torch/train_step.py --model "$model" --steps 20 --device cuda $phases
  done
  case " $COMPILE_MODELS " in *" $model "*)
    timeout 150 python3 benches/torch/train_step.py --model "$model" --steps 20 --device cuda --compile $phases;;
  esac
done >> "$OUT/bench.jsonl" 2> "$OUT/bench.err"
python3 - "$OUT/bench.jsonl" >> "$OUT/summary.txt" <<'PY'
import json, statistics, sys
rows = []
for line in open(sys.argv[1]):
    try:
        rows.append(json.loads(line))
    except ValueError:
        pass
for model in sorted({r["model"] for r in rows}):
    impls = sorted({r["impl"] for r in rows if r["model"] == model})
    for impl in impls:
        v = [r["median_s"] for r in rows if r["model"] == model and r["impl"] == impl]
        print(f"{model:10s} {impl:40s} runs {len(v)} median {1e3 * statistics.median(v):8.3f} ms/step")
PY
stamp "benches done"

# The NeRF example's time-to-PSNR runs: the committed dataset (its default scene box,
# the visual hull's), then, if present, its 400 × 400 rendering (NERF400, default
# .gpu/wuson400: `blender -b -P examples/data/render_dataset.py -- --out .gpu/wuson400
# --resolution 400`).
NERF400=${NERF400:-.gpu/wuson400}
if [ -x "$BIN/nerf" ]; then
  minutes=$(python3 -c "print($NERF_SECONDS / 60)")
  for set in nerf nerf400; do
    data=examples/data/wuson; [ "$set" = nerf400 ] && data=$NERF400
    [ -d "$data" ] || continue
    for rays in $NERF_RAYS; do
      # nerf, nerf400 at 1024 rays per step; nerf_r8192 and so on at other batches.
      run=$set; [ "$rays" = 1024 ] || run=${set}_r$rays
      [ "$set" = nerf400 ] && [ "$rays" != 1024 ] && continue
      stamp "$run: the NeRF example on $data, $NERF_SECONDS s, $rays rays per step"
      timeout $(( NERF_SECONDS + 150 )) "$BIN/nerf" --data "$data" --device cuda \
        --minutes "$minutes" --rays "$rays" --out "/tmp/$run-gpu" > "$OUT/$run.log" 2>&1
      stamp "rc=$? $(tail -2 "$OUT/$run.log" | tr '\n' ' ')"
      cp "/tmp/$run-gpu/metrics.json" "$OUT/${run}_metrics.json" 2>/dev/null
      cp "/tmp/$run-gpu/curve.csv" "$OUT/${run}_curve.csv" 2>/dev/null
    done
  done
fi
stamp "done"

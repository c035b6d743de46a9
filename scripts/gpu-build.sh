#!/usr/bin/env bash
# Builds, with the `cuda` feature, the binaries that scripts/gpu-check.sh runs on a GPU
# machine (tests/cuda.rs, benches/train_step.rs, the NeRF example) and copies them,
# stripped and xz-compressed (each holds candle's PTX: about 60 MB, 7 MB compressed), to
# .gpu/. Works without a GPU given a CUDA toolkit (scripts/cuda-toolchain.sh).
#
#     scripts/gpu-build.sh            # CUDA_HOME defaults to /opt/cuda13, compute cap 90
set -euo pipefail
cd "$(dirname "$0")/.."
export CUDA_HOME=${CUDA_HOME:-/opt/cuda13}
export PATH=$CUDA_HOME/bin:$PATH CUDA_COMPUTE_CAP=${CUDA_COMPUTE_CAP:-90}
mkdir -p .gpu
cargo build --release --features cuda --target-dir target/cuda \
  --test cuda --bench train_step --example nerf --message-format=json \
  | python3 -c '
import json, shutil, subprocess, sys
for line in sys.stdin:
    try:
        m = json.loads(line)
    except ValueError:
        continue
    if m.get("reason") == "compiler-message" and m["message"]["level"] in ("error", "warning"):
        print(m["message"]["rendered"], file=sys.stderr)
    exe = m.get("executable") if m.get("reason") == "compiler-artifact" else None
    if exe:
        name = m["target"]["name"]
        shutil.copy(exe, ".gpu/" + name)
        subprocess.run(["strip", ".gpu/" + name], check=True)
        subprocess.run(["xz", "-f", "-T2", "-6", ".gpu/" + name], check=True)
        print("built", ".gpu/" + name + ".xz")
'
ls -la .gpu

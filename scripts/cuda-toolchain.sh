#!/usr/bin/env bash
# Builds a CUDA 13.0 toolkit from PyPI wheels into one directory, so that the `cuda`
# feature compiles (and its test binaries link) on a machine with no GPU and no CUDA
# installation. Usage:
#
#     scripts/cuda-toolchain.sh [PREFIX]          # default PREFIX: /opt/cuda13
#     export CUDA_HOME=PREFIX PATH=PREFIX/bin:$PATH CUDA_COMPUTE_CAP=90
#     cargo test --release --features cuda --no-run
#
# Needs python3 with pip, unzip and a C compiler (for the libcuda link stub). The
# binaries it builds load the real driver's libcuda.so.1 at run time; see docs/cuda.md.
set -euo pipefail
prefix=${1:-/opt/cuda13}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

wheels=(
  nvidia-cuda-nvcc==13.0.88
  nvidia-nvvm==13.0.88
  nvidia-cuda-crt==13.0.88
  nvidia-cuda-runtime==13.0.96
  nvidia-cuda-cccl==13.0.85
  nvidia-cublas==13.0.2.14
  nvidia-curand==10.4.0.35
  nvidia-cuda-nvrtc==13.0.88
)
python3 -m pip download -q --no-deps --only-binary=:all: \
  --platform manylinux_2_27_x86_64 --platform manylinux_2_28_x86_64 \
  --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 \
  --python-version 3.12 -d "$work/whl" "${wheels[@]}"

mkdir -p "$prefix"
for w in "$work"/whl/*.whl; do
  rm -rf "$work/x"
  unzip -q -o "$w" -d "$work/x"
  for root in "$work"/x/nvidia/cu13 "$work"/x/nvidia/*/; do
    if [ -d "$root/bin" ] || [ -d "$root/include" ] || [ -d "$root/lib" ] || [ -d "$root/nvvm" ]; then
      cp -a "$root/." "$prefix/"
      break
    fi
  done
done
chmod +x "$prefix"/bin/* "$prefix"/nvvm/bin/* 2>/dev/null || true
[ -d "$prefix/lib64" ] || ln -sfn lib "$prefix/lib64"

# Linker names: the wheels ship only versioned sonames.
cd "$prefix/lib"
for base in cudart nvrtc cublas cublasLt curand; do
  so=$(ls lib$base.so.* 2>/dev/null | sort | head -n1 || true)
  [ -n "$so" ] && ln -sfn "$so" "lib$base.so"
done

# A libcuda.so link stub: candle links cudarc with dynamic linking, and the wheels carry
# no driver. Empty functions named after every cu* symbol cudarc declares; soname
# libcuda.so.1, so the real driver is loaded at run time.
# cudarc's sources must be in cargo's registry: fetch them (with the rest of Cargo.lock)
# first, and refuse to write an empty stub (binaries would then fail to link with
# undefined `cu*` symbols).
(cd "$(dirname "$0")/.." && cargo fetch -q)
syms=$(grep -rhoE '\bcu[A-Z][A-Za-z0-9_]+\b' "${CARGO_HOME:-$HOME/.cargo}"/registry/src/*/cudarc-*/src/driver/sys/ 2>/dev/null | sort -u || true)
if [ -z "$syms" ]; then
  echo "cuda-toolchain.sh: no cudarc sources under ${CARGO_HOME:-$HOME/.cargo}/registry/src; cannot write the libcuda stub" >&2
  exit 1
fi
{
  for s in $syms; do echo "void $s(void) {}"; done
} > "$work/stub.c"
cc -shared -fPIC -Wl,-soname,libcuda.so.1 -o "$prefix/lib/libcuda.so" "$work/stub.c"
mkdir -p "$prefix/lib/stubs" && cp "$prefix/lib/libcuda.so" "$prefix/lib/stubs/"
"$prefix/bin/nvcc" --version | tail -n2
echo "CUDA toolkit ready in $prefix"

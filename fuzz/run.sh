#!/usr/bin/env bash
# Seeds a target's corpus and fuzzes it with libFuzzer (cargo fuzz), one job.
#
#   fuzz/run.sh TARGET SECONDS        # targets: ply obj stl off transforms_json cameras_npz dataset_image
#
# Needs cargo-fuzz (`cargo install cargo-fuzz`); RUSTC_BOOTSTRAP=1 lets the stable
# toolchain take the -Z flags cargo-fuzz passes. The readers are safe Rust, so the
# build has no sanitizer (-s none: several times more executions per second); what the
# fuzzer looks for is panics, hangs (-timeout, seconds per input) and memory beyond
# -rss_limit_mb. Corpora and findings stay under fuzz/corpus and fuzz/artifacts
# (ignored by git); every finding becomes a regression test named after the defect.
# The log of each run is appended to fuzz/logs/TARGET.log.
set -euo pipefail
cd "$(dirname "$0")"
target=${1:?target}
seconds=${2:?seconds}
corpus=corpus/$target
mkdir -p "$corpus" logs artifacts/"$target"
models=/usr/share/assimp/models
seed() { # seed FILE...: copies files under 64 KiB into the corpus
  for f in "$@"; do
    [ -f "$f" ] && [ "$(stat -c %s "$f")" -le 65536 ] && cp -n "$f" "$corpus/seed-$(basename "$f")" || true
  done
}
case "$target" in
  ply) seed "$models"/PLY/*.ply ;;
  obj) seed "$models"/OBJ/*.obj ;;
  stl) seed "$models"/STL/* ;;
  off) seed "$models"/OFF/* ;;
  transforms_json)
    # First byte 0: Blender layout; 1: nerfstudio.
    for f in ../examples/data/wuson/transforms_*.json; do
      { printf '\0'; cat "$f"; } >"$corpus/seed-blender-$(basename "$f")"
    done
    printf '\1{"fl_x":50,"fl_y":50,"cx":50,"cy":50,"w":100,"h":100,"frames":[{"file_path":"img.png","transform_matrix":[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]}]}' \
      >"$corpus/seed-nerfstudio.json" ;;
  cameras_npz) seed ../examples/data/wuson_dtu/cameras.npz ;;
  dataset_image) seed ../examples/data/wuson/train/r_0.png ../examples/data/wuson_dtu/image/000000.png ;;
  *) echo "unknown target $target" >&2; exit 2 ;;
esac
RUSTC_BOOTSTRAP=1 cargo fuzz build -s none --fuzz-dir . "$target" >/dev/null 2>&1 \
  || RUSTC_BOOTSTRAP=1 cargo fuzz build -s none --fuzz-dir . "$target"
start=$(date +%s)
{
  echo "== $(date -u +%FT%TZ) $target for ${seconds}s ($(git rev-parse --short HEAD))"
  /usr/bin/time -f "%U %S" -o "logs/$target.cpu" \
    ./target/x86_64-unknown-linux-gnu/release/"$target" "$corpus" \
    -max_total_time="$seconds" -max_len=65536 -timeout=10 -rss_limit_mb=2048 \
    -artifact_prefix=artifacts/"$target"/ -print_final_stats=1 2>&1 | grep -v -e '^#[0-9]' -e '^"' || true
  echo "== end: $(($(date +%s) - start)) s fuzzed"
  # CPU seconds (user + system): less than the wall time when fuzzers share the cores.
  if [ -f "logs/$target.cpu" ]; then
    tail -n 1 "logs/$target.cpu" | awk '{ printf "== cpu: %d s\n", $1 + $2 }'
  fi
} | tee -a logs/"$target".log

#!/usr/bin/env bash
# Render the scene suite: six multi-view scenes (Blender synthetic layout, 100 x 100 RGBA,
# 50 / 10 / 20 views) of assimp-testmodels meshes, chosen to differ from each other, with
# examples/data/render_dataset.py, one after another, then write OUT/suite.json.
#
#     bash examples/data/render_suite.sh [OUT]        (default OUT: examples/data/suite)
#
# Needs Blender 3.4 (`blender`, or $BLENDER) and Debian's assimp-testmodels
# (/usr/share/assimp/models, or $ASSIMP_MODELS).  Every scene is rendered with
# --seed 0 --no-dtu; the run is deterministic (two runs give byte-identical files).
# The tuning scenes are for choosing settings, the report scenes for reporting results
# with the settings so chosen.
set -euo pipefail

OUT=${1:-examples/data/suite}
HERE=$(cd "$(dirname "$0")" && pwd)
MODELS=${ASSIMP_MODELS:-/usr/share/assimp/models}
BLENDER=${BLENDER:-blender}

# name | set | mesh (under $MODELS) | file's up axis | material | object radius | property
SCENES=(
  "wuson|tuning|PLY/Wuson.ply|Y|bands|1.0|an object that fills about a tenth of the frame (the committed examples/data/wuson scene)"
  "stick|tuning|STL/3DSMaxExport.STL|Z|bands|1.0|thin structures"
  "shapes|tuning|Collada/Cinema4D.dae|Z|fine|1.0|fine texture"
  "teapots|report|Collada/teapot_instancenodes.DAE|Z|bands|1.25|concavities and holes"
  "plate|report|Collada/COLLADA.dae|Z|bands|1.3|large flat faces"
  "duck|report|Collada/duck.dae|Z|glossy|1.6|a glossy material; an object that fills the frame"
)

mkdir -p "$OUT"
for spec in "${SCENES[@]}"; do
  IFS='|' read -r name set mesh up material radius property <<< "$spec"
  if [ ! -f "$MODELS/$mesh" ]; then
    echo "missing mesh $MODELS/$mesh (Debian package assimp-testmodels)" >&2
    exit 1
  fi
  rm -rf "${OUT:?}/$name"
  echo "== $name: $mesh, material $material, object radius $radius" >&2
  start=$(date +%s%N)
  "$BLENDER" -b -P "$HERE/render_dataset.py" -- \
    --mesh "$MODELS/$mesh" --out "$OUT/$name" --seed 0 --no-dtu \
    --up-axis "$up" --material "$material" --object-radius "$radius" \
    > "$OUT/.$name.log" 2>&1 || { tail -20 "$OUT/.$name.log" >&2; exit 1; }
  grep '^rendered' "$OUT/.$name.log" >&2 || true
  rm -f "$OUT/.$name.log"
  ms=$(( ($(date +%s%N) - start) / 1000000 ))
  printf "%s: %d.%03d s wall\n" "$name" $((ms / 1000)) $((ms % 1000)) >&2
done

# suite.json (no render times in it, so that it too is reproducible)
python3 - "$OUT" "$MODELS" "${SCENES[@]}" <<'EOF'
import hashlib
import json
import os
import sys

out, models, specs = sys.argv[1], sys.argv[2], sys.argv[3:]
doc = {"tuning": [], "report": [], "scenes": {}}
for spec in specs:
    name, split, mesh, up, material, radius, prop = spec.split("|")
    path = os.path.join(models, mesh)
    with open(path, "rb") as f:
        sha = hashlib.sha256(f.read()).hexdigest()
    doc[split].append(name)
    doc["scenes"][name] = {
        "mesh": path,
        "mesh_sha256": sha,
        "mesh_up_axis": up,
        "material": material,
        "object_radius": float(radius),
        "property": prop,
        "set": split,
        "seed": 0,
        "views": {"train": 50, "val": 10, "test": 20},
    }
with open(os.path.join(out, "suite.json"), "w") as f:
    json.dump(doc, f, indent=1)
    f.write("\n")
print("wrote %s: tuning %s, report %s" % (os.path.join(out, "suite.json"),
                                           ", ".join(doc["tuning"]), ", ".join(doc["report"])))
EOF

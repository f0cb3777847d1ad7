#!/usr/bin/env bash
# From one mesh file to poses, on a laptop CPU: import the mesh, simulate an AR capture of it, label the
# frames, train the default two-stage detector in a short budget, evaluate it, predict one frame.
#
#   bash examples/custom_object/run.sh        # from the repository root, after `make install`
#
# MESH=path/to/your.obj (any of OBJ, STL, PLY, GLB, OFF) uses your own mesh instead of the example's.
# Every step resumes when run again. The timings of each step go to data/custom/times.txt.
set -euo pipefail
cd "$(dirname "$0")/../.."
A=.venv/bin/argen
D=.venv/bin/detector
OUT=${OUT:-data/custom}
RUNS=${RUNS:-runs/custom}
S1=${STAGE1_STEPS:-2000}     # the budget: stage 1 (find the object, its centre) and stage 2 (pose in crops)
S2=${STAGE2_STEPS:-6000}
mkdir -p "$OUT"
T="$OUT/times.txt"
step() { local name=$1; shift; local t0=$SECONDS; "$@"; echo "$name $((SECONDS - t0)) s" | tee -a "$T"; }

# 0. the mesh: yours, or the example's (LineMOD's duck written as a plain OBJ file in metres)
MESH=${MESH:-$OUT/mesh/duck.obj}
[ -f "$MESH" ] || .venv/bin/python examples/custom_object/make_mesh.py "$MESH"
NAME=$(basename "${MESH%.*}")

# 1. import: BOP models folder in mm, units decided and symmetries searched (read what it prints)
step import $A models import "$MESH" --out "$OUT/models"

# 2. simulated AR captures of it (linemod template: marker board, desk clutter, Kinect v1 noise)
step capture_train $A capture-sim --scene linemod --models "$OUT/models" --objects "$NAME" --frames 600 --seed 1 \
  --workers 2 --out "$OUT/train" --quiet
step capture_test $A capture-sim --scene linemod --models "$OUT/models" --objects "$NAME" --frames 100 --seed 2 \
  --workers 2 --out "$OUT/test" --quiet

# 3. per-point labels
for s in train test; do
  [ -f "$OUT/$s.h5" ] || step "label_$s" $A label "$OUT/$s" --out "$OUT/$s.h5" --quiet
done

# 4. train the default detector (both stages) within the budget
if [ ! -f "$RUNS/model.pt" ]; then
  R=""; [ -f "$RUNS/two_stage.yaml" ] && R="--resume"
  step train $D train "$OUT/train.h5" --out "$RUNS" --set stage1.steps=$S1 --set stage2.steps=$S2 $R --quiet
fi

# 5. evaluate on the held-out capture (another seed), with ICP refinement
step eval $D eval "$RUNS/model.pt" "$OUT/test.h5" --out "$OUT/report" --icp --quiet
grep -E "ADD|F1|recall|precision" "$OUT/report/report.md" | head -n 12 || true

# 6. one frame: poses.json and a picture of the boxes (poses.png)
step predict $D predict "$RUNS/model.pt" "$OUT/test/train_pbr/000000/000003" --out "$OUT/predict" --icp

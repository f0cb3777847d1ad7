#!/usr/bin/env bash
# From one mesh file to poses, on a laptop CPU: import the mesh, simulate AR captures of it, label the
# frames, train the two-stage detector as examples/ycbv_real/run.sh does for real sensors (both stages on geometry
# only, stage 1 on a capture without distractors) in a short budget, evaluate it, predict one frame.
#
#   bash examples/custom_object/run.sh        # from the repository root, after `make install`
#
# MESH=path/to/your.obj (any of OBJ, STL, PLY, GLB, OFF) uses your own mesh instead of the example's.
# RECIPE=default trains `detector train`'s default instead (colour in both stages, stage 1 among distractors, 6000
# stage-2 steps: better on simulated frames, far worse on real ones; README), into runs/custom_default.
# Every step resumes when run again. The timings of each step go to data/custom/times.txt.
set -euo pipefail
cd "$(dirname "$0")/../.."
A=.venv/bin/argen
D=.venv/bin/detector
OUT=${OUT:-data/custom}
RECIPE=${RECIPE:-real}
S1=${STAGE1_STEPS:-2000}     # the budget: stage 1 (find the object, its centre) and stage 2 (pose in crops)
# DATA: the train step's label files besides the training capture's; SETS: its settings besides the budget
case $RECIPE in
  real) RUNS=${RUNS:-runs/custom}; S2=${STAGE2_STEPS:-4000}; REP=$OUT/report
        DATA=(--stage1-data "$OUT/stage1.h5")
        SETS=(--set stage1.colour=none --set stage1.plane_keep=0.1 --set stage2.crop.colour=none) ;;
  default) RUNS=${RUNS:-runs/custom_default}; S2=${STAGE2_STEPS:-6000}; REP=$OUT/report_default; DATA=(); SETS=() ;;
  *) echo "RECIPE must be real or default, got $RECIPE" >&2; exit 2 ;;
esac
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
#    and the training capture again without distractors, for stage 1 alone: a stage 1 that learns among distractors
#    finds far less of the objects in real frames (RESULTS.md, "The default recipe on these frames")
[ $RECIPE = default ] || step capture_stage1 $A capture-sim --scene linemod --models "$OUT/models" --objects "$NAME" \
  --frames 600 --seed 1 --workers 2 --out "$OUT/stage1" --quiet --set clutter.count=[0,0] --set clutter.on_board=[0,0]

# 3. per-point labels
for s in train stage1 test; do
  [ -f "$OUT/$s.h5" ] || [ ! -d "$OUT/$s" ] || step "label_$s" $A label "$OUT/$s" --out "$OUT/$s.h5" --quiet
done

# 4. train both stages within the budget, on geometry only (colour from another camera cannot mislead them), stage 1
#    on the capture without distractors and seeing a tenth of the desk plane, stage 2 among the distractors: the
#    settings of examples/ycbv_real/run.sh, which were chosen on real frames (RESULTS.md)
#    (RECIPE=default: `detector train`'s default settings, both stages on the training capture)
if [ ! -f "$RUNS/model.pt" ]; then  # a run begun before is resumed with the settings it started with
  [ -f "$RUNS/two_stage.yaml" ] && SETS=(--resume)
  step train $D train "$OUT/train.h5" "${DATA[@]}" --out "$RUNS" "${SETS[@]}" --set stage1.steps=$S1 \
    --set stage2.steps=$S2 --quiet
fi

# 5. evaluate on the held-out capture (another seed), with ICP refinement
step eval $D eval --reuse "$RUNS/model.pt" "$OUT/test.h5" --out "$REP" --icp --quiet
grep -E "ADD|F1|recall|precision" "$REP/report.md" | head -n 12 || true

# 6. one frame: poses.json and a picture of the boxes (poses.png)
step predict $D predict "$RUNS/model.pt" "$OUT/test/train_pbr/000000/000003" --out "$REP/predict" --icp

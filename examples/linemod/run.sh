#!/usr/bin/env bash
# The accuracy study of RESULTS.md, end to end: simulated LineMOD-style captures of the 8 real LineMOD
# objects (training and held-out test data with different seeds, Kinect noise on), per-point labels,
# one cpu-preset model for all 8 objects, evaluation without and with ICP, and the LC-HF-style F1.
#
#   bash examples/linemod/run.sh            # from the repository root, after `make install`
#
# Every step resumes when run again (and refuses to overwrite other options).
# STEPS sets the training length (RESULTS.md: 9500 steps, about 70 minutes on the 2-core study machine).
set -euo pipefail
cd "$(dirname "$0")/../.."
A=.venv/bin/argen
D=.venv/bin/detector
M=${MODELS:-../shared/data/lm/models}      # BOP LineMOD models (mm)
OUT=${OUT:-data}
STEPS=${STEPS:-9500}
mkdir -p "$OUT"

# 1. simulated AR captures (BOP format); seeds differ between train and test
$A capture-sim --scene linemod --models "$M" --frames 3000 --seed 1 --workers 2 --out "$OUT/lm_train" --quiet
$A capture-sim --scene linemod --models "$M" --frames 300  --seed 2 --workers 2 --out "$OUT/lm_test"  --quiet
$A capture-sim --scene lchf    --models "$M" --frames 150  --seed 3 --workers 2 --out "$OUT/lchf_test" --quiet

# 2. per-point labels (16384 points per frame)
for s in lm_train lm_test lchf_test; do
  [ -f "$OUT/$s.h5" ] || $A label "$OUT/$s" --out "$OUT/$s.h5" --max-points 16384 --quiet
done

# 3. one model for all 8 objects, cpu preset
if [ -f runs/lm_cpu/last.pt ]; then   # an interrupted run continues with its own config.yaml
  $D train "$OUT/lm_train.h5" --out runs/lm_cpu --resume
else
  $D train "$OUT/lm_train.h5" --out runs/lm_cpu --preset cpu --steps "$STEPS" --workers 1 \
    --set checkpoint_every=250
fi

# 4. evaluation: the paper's tau 0.8, and tau 0 (every point classified as an object votes; RESULTS.md
#    explains why), linemod test set with and without ICP, lchf test set for the F1
$D eval runs/lm_cpu/last.pt "$OUT/lm_test.h5"   --out reports/lm_test        --icp --quiet
$D eval runs/lm_cpu/last.pt "$OUT/lm_test.h5"   --out reports/lm_test_tau0   --icp --tau 0 --quiet
$D eval runs/lm_cpu/last.pt "$OUT/lchf_test.h5" --out reports/lchf_test      --icp --quiet
$D eval runs/lm_cpu/last.pt "$OUT/lchf_test.h5" --out reports/lchf_test_tau0 --icp --tau 0 --quiet

# 5. the tables of RESULTS.md (with the paper's numbers beside ours)
.venv/bin/python examples/linemod/tables.py reports/lm_test_tau0/report.json reports/lchf_test_tau0/report.json \
  --run runs/lm_cpu

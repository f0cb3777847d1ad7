# Sourced by the examples' run.sh scripts (from the repository root).
# stage1_beside FROM R TRAIN_FILE STAGE1_YAML STAGE1_FILE...: stage 1 alone trained beside the finished stage 2 of the
# run folder FROM. R gets a copy of FROM's stage2 folder and FROM's two_stage.yaml with STAGE1_YAML (a YAML mapping,
# "{}" for none) merged into its stage1 section; `detector train TRAIN_FILE --stage1-data STAGE1_FILE ... --resume`
# then trains stage 1 and, the copied stage being finished, only assembles R/model.pt. Nothing is done where
# R/model.pt exists. The two stages train independently, so R/model.pt is what one `detector train` of both stages
# with that stage 1 would give (each stage from its own seed). PYTHON and DETECTOR name the interpreter and the
# detector command (default: the repository's .venv).
stage1_beside() {
  local from=$1 r=$2 train=$3 sets=$4 f data=()
  shift 4
  for f in "$@"; do data+=(--stage1-data "$f"); done
  [ -f "$r/model.pt" ] && return 0
  [ -d "$r/stage2" ] || { mkdir -p "$r" && cp -r "$from/stage2" "$r/"; }
  "${PYTHON:-.venv/bin/python}" -c "import sys, yaml; c = yaml.safe_load(open(sys.argv[1])) or {}; \
c['stage1'] = {**(c.get('stage1') or {}), **(yaml.safe_load(sys.argv[2]) or {})}; \
yaml.safe_dump(c, open(sys.argv[3], 'w'), sort_keys=False)" "$from/two_stage.yaml" "$sets" "$r/two_stage.yaml"
  "${DETECTOR:-.venv/bin/detector}" train "$train" "${data[@]}" --out "$r" --resume --quiet
}

#!/usr/bin/env bash
# The shipped model, end to end: data (if missing), training for a fixed number of steps in three
# stages (the v3 preset, 24,000 steps; its export fine-tuned by the v3-finetune preset, 8,000
# more steps from 0.3 of the learning rate; that export's h alone fine-tuned on 512 points by the
# v3-h512 preset, 6,000 steps), export (f and g take 256 points, h 512); then the
# leave-one-style-out model of the benchmark (docs/benchmark.md), trained the same three-stage
# way on a split that holds out one style per category, and exported for evaluation only.
# Between the two, g's category head alone is refitted with outside furniture (outside.sh:
# Scopia's and Kator & Legaz's models from Debian's sweethome3d-furniture, which must be
# installed) beside the training shapes (`complementme category-head`, under a minute).
#
#   training/recipes/shipped.sh                 # defaults below
#   OUT=exported training/recipes/shipped.sh
#
# The presets fix the number of steps: the same seed and thread count give the same model on the
# same kind of host (CPU kernels differ between AVX2 and AVX-512, and between AMD's and Intel's
# AVX-512 hosts: the second stage run again on an Intel one scored 0.010 lower functional mAP@5,
# docs/training.md). Every run trains on two
# threads, one after the other: the shipped model's first stage took 104 min alone on a 2-core
# AVX-512 host (0.19 s a step, against 0.45-0.6 s for one thread beside other work), its second
# stage 20 min, its third 21 min beside other work; the thread count is part of the recipe because torch's reductions may round
# differently on another count. The presets' time guards (max_minutes) only stop a run far
# slower than planned, with a warning in the log. If one is interrupted,
# `python -m training train --resume --run "$RUN"` continues it.
set -euo pipefail

PYTHON=${PYTHON:-python}
RAW=${RAW:-data/raw}
DATA=${DATA:-data/processed}
RUN=${RUN:-runs/v3}
LOSO_RUN=${LOSO_RUN:-runs/v3-loso}
OUT=${OUT:-exported}
LOSO_OUT=${LOSO_OUT:-runs/v3-loso-h512-exported}  # earlier stages export to <stage run>-exported
SEED=${SEED:-0}
THREADS=${THREADS:-2}
LOG=${LOG:-runs/recipe.log}
HEAD_DATA=${HEAD_DATA:-data/real-train}  # the outside furniture the category head is refitted on
source "$(dirname "$0")/outside.sh"

if [ ! -f "$DATA/dataset.json" ]; then
    if [ ! -d "$RAW" ]; then
        "$PYTHON" -m training data generate --out "$RAW" --seed "$SEED"
    fi
    "$PYTHON" -m training data preprocess --raw "$RAW" --out "$DATA" --seed "$SEED"
fi

for run in "$RUN" "$RUN-finetune" "$RUN-h512" "$LOSO_RUN" "$LOSO_RUN-finetune" "$LOSO_RUN-h512"; do
    if [ -f "$run/checkpoint.pt" ]; then
        echo "error: $run already holds a run; resume it with --resume or choose RUN=... / LOSO_RUN=..." >&2
        exit 2
    fi
done
check_furniture "$HEAD_DATA" "${HEAD_LIBRARIES[@]}"  # before hours of training, not after
mkdir -p "$(dirname "$LOG")"
train() {  # preset, run-folder, extra options...
    local preset=$1 run=$2 start
    shift 2
    start=$(date +%s)
    "$PYTHON" -m training train --preset "$preset" --threads "$THREADS" --no-progress --data "$DATA" \
        --run "$run" --seed "$SEED" "$@" > "$run.log" 2>&1
    echo "$run trained in $(( ($(date +%s) - start) / 60 )) min, $THREADS threads of $(nproc) cores" \
         "($(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs))" | tee -a "$LOG"
}
three_stages() {  # run-folder, export-folder, extra options...: each stage from the last one's export
    local run=$1 out=$2
    shift 2
    train v3 "$run" "$@"
    "$PYTHON" -m training export --run "$run" --out "$run-exported"
    train v3-finetune "$run-finetune" --init-from "$run-exported" "$@"
    "$PYTHON" -m training export --run "$run-finetune" --out "$run-finetune-exported"
    train v3-h512 "$run-h512" --init-from "$run-finetune-exported" "$@"
    "$PYTHON" -m training export --run "$run-h512" --out "$out" --n-points 256 --placement-points 512
}
three_stages "$RUN" "$OUT"
outside_furniture "$HEAD_DATA" "${HEAD_LIBRARIES[@]}"
"$PYTHON" -m training category-head --artifacts "$OUT" --run "$RUN-h512" --outside "$HEAD_DATA/processed" \
    --out "$OUT" --seed "$SEED"
three_stages "$LOSO_RUN" "$LOSO_OUT" --split styles

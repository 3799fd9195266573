#!/usr/bin/env bash
# The shipped model, end to end: data (if missing), training within a wall-clock budget, export.
#
#   training/recipes/shipped.sh                 # defaults below (60 minutes of training)
#   MINUTES=60 OUT=exported training/recipes/shipped.sh
#
# Training stops after MINUTES of this invocation (or at the preset's step cap) and leaves a
# checkpoint; if it is interrupted, `python -m training train --resume --run "$RUN" --minutes M`
# continues it. Every step is seeded: the same data and budget give the same model up to how
# many steps fit in the budget on the machine.
set -euo pipefail

PYTHON=${PYTHON:-python}
RAW=${RAW:-data/raw}
DATA=${DATA:-data/processed}
RUN=${RUN:-runs/shipped}
OUT=${OUT:-exported}
MINUTES=${MINUTES:-60}
SEED=${SEED:-0}

if [ ! -f "$DATA/dataset.json" ]; then
    if [ ! -d "$RAW" ]; then
        "$PYTHON" -m training data generate --out "$RAW" --seed "$SEED"
    fi
    "$PYTHON" -m training data preprocess --raw "$RAW" --out "$DATA" --seed "$SEED"
fi

if [ -f "$RUN/checkpoint.pt" ]; then
    echo "error: $RUN already holds a run; resume it with --resume or choose RUN=..." >&2
    exit 2
fi
"$PYTHON" -m training train --preset shipped --data "$DATA" --run "$RUN" --seed "$SEED" --minutes "$MINUTES"
"$PYTHON" -m training export --run "$RUN" --out "$OUT"

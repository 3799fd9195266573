#!/usr/bin/env bash
# Shapes nobody here made (docs/benchmark-real/benchmark.md): Sweet Home 3D's free furniture
# libraries, as Debian packages them, filed as OBJ folders by category, ingested and preprocessed
# like any user collection, then asked of the shipped engine beside as many held-out catalog
# shapes. Needs `apt-get install -y sweethome3d-furniture` (120 MB of CC0 and CC-BY models; or
# `apt-get download sweethome3d-furniture && dpkg -x sweethome3d-furniture_*.deb root` and
# LIBRARIES=root/usr/share/sweethome3d/furniture without root rights).
#
#   training/recipes/real.sh                     # defaults below
#   ARTIFACTS=runs/x-exported OUT=/tmp/real training/recipes/real.sh
set -euo pipefail

PYTHON=${PYTHON:-python}
LIBRARIES=${LIBRARIES:-/usr/share/sweethome3d/furniture}
DATA=${DATA:-data/real}
ARTIFACTS=${ARTIFACTS:-exported}
OUT=${OUT:-docs/benchmark-real}
SEED=${SEED:-0}

if [ ! -f "$DATA/processed/dataset.json" ]; then
    rm -rf "$DATA/src" "$DATA/raw"
    "$PYTHON" -m training data sweethome3d "$LIBRARIES" --out "$DATA/src"
    "$PYTHON" -m training data ingest "$DATA/src" --out "$DATA/raw" --ignore-obj-materials
    "$PYTHON" -m training data preprocess --raw "$DATA/raw" --out "$DATA/processed" --seed "$SEED"
fi
"$PYTHON" -m training evaluate-real --data "$DATA/processed" --artifacts "$ARTIFACTS" --out "$OUT" --seed "$SEED"

#!/usr/bin/env bash
# Shapes nobody here made (docs/benchmark-real/benchmark.md): Sweet Home 3D's free furniture
# libraries (BlendSwap's contributors': the makers g's category head is not refitted on, see
# outside.sh) and FlightGear's AI aircraft, as Debian packages them, filed as OBJ folders by
# category, ingested and preprocessed like any user collection, then asked of the shipped engine
# beside as many held-out catalog shapes. Needs `apt-get install -y sweethome3d-furniture
# flightgear-data-ai` (120 MB of CC0 and CC-BY furniture, 290 MB of GPL aircraft; or `apt-get
# download` both, `dpkg -x` each into a folder, and FURNITURE=... AIRCRAFT=... without root rights).
#
#   training/recipes/real.sh                     # defaults below
#   ARTIFACTS=runs/x-exported OUT=/tmp/real training/recipes/real.sh
set -euo pipefail

PYTHON=${PYTHON:-python}
AIRCRAFT=${AIRCRAFT:-/usr/share/games/flightgear/AI/Aircraft}
DATA=${DATA:-data/real-test}  # the furniture makers the category head never saw (outside.sh)
AIR_DATA=${AIR_DATA:-data/real-air}
ARTIFACTS=${ARTIFACTS:-exported}
OUT=${OUT:-docs/benchmark-real}
SEED=${SEED:-0}
source "$(dirname "$0")/outside.sh"

outside_furniture "$DATA" "${HELD_OUT_LIBRARIES[@]}"
if [ ! -f "$AIR_DATA/processed/dataset.json" ]; then
    rm -rf "$AIR_DATA/src" "$AIR_DATA/raw"
    "$PYTHON" -m training data flightgear "$AIRCRAFT" --out "$AIR_DATA/src"
    "$PYTHON" -m training data ingest "$AIR_DATA/src" --out "$AIR_DATA/raw"
    "$PYTHON" -m training data preprocess --raw "$AIR_DATA/raw" --out "$AIR_DATA/processed" --seed "$SEED"
fi
"$PYTHON" -m training evaluate-real --data "$DATA/processed" --artifacts "$ARTIFACTS" --out "$OUT" --seed "$SEED"
"$PYTHON" -m training evaluate-real --data "$AIR_DATA/processed" --artifacts "$ARTIFACTS" --out "$OUT/airplanes" \
    --seed "$SEED"

# The outside furniture (docs/benchmark-real): Debian's Sweet Home 3D libraries
# (`apt-get install -y sweethome3d-furniture`), split by maker so that no maker's models are on
# both sides. g's category head is refitted on Scopia's and Kator & Legaz's models (CC-BY 3.0;
# training.category_head, called by shipped.sh); the BlendSwap contributors' (CC0 and CC-BY 3.0)
# are held out, for evaluate-real (real.sh). Sourced by both, after PYTHON and SEED are set.
FURNITURE=${FURNITURE:-/usr/share/sweethome3d/furniture}
HEAD_LIBRARIES=(Scopia KatorLegaz)
HELD_OUT_LIBRARIES=(BlendSwap-CC-0 BlendSwap-CC-BY)

check_furniture() {  # folder, libraries...: exits naming a missing library unless <folder> is made
    local folder=$1 lib
    shift
    [ -f "$folder/processed/dataset.json" ] && return
    for lib in "$@"; do
        if [ ! -f "$FURNITURE/$lib.sh3f" ]; then
            echo "error: $FURNITURE/$lib.sh3f is missing: apt-get install -y sweethome3d-furniture" \
                 "(or FURNITURE=<folder of .sh3f files>)" >&2
            exit 2
        fi
    done
}

outside_furniture() {  # folder, libraries...: filed, ingested and preprocessed into <folder>/processed
    local folder=$1 lib
    check_furniture "$@"
    shift
    [ -f "$folder/processed/dataset.json" ] && return
    local paths=()
    for lib in "$@"; do
        paths+=("$FURNITURE/$lib.sh3f")
    done
    rm -rf "$folder/src" "$folder/raw"
    "$PYTHON" -m training data sweethome3d "${paths[@]}" --out "$folder/src"
    "$PYTHON" -m training data ingest "$folder/src" --out "$folder/raw" --ignore-obj-materials
    "$PYTHON" -m training data preprocess --raw "$folder/raw" --out "$folder/processed" --seed "$SEED"
}

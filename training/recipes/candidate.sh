#!/usr/bin/env bash
# Everything a trained candidate must show before it may replace exported/ (docs/training.md,
# "Shipping a candidate"): its export, the committed benchmark in the shipped model's own order,
# its leave-one-style-out twin, automatic assembly, frame fitting, the furniture nobody here made
# (when training/recipes/real.sh has made data/real-test), and the service's tests on it.
# Nothing in exported/ or docs/ is touched: every result goes under the candidate's folders.
#
#   RUN=runs/v3-32k LOSO_RUN=runs/v3-32k-loso training/recipes/candidate.sh
#
# About 30 minutes on a 2-core host beside two one-thread trainings (the benchmark 13, its twin 5,
# the service tests 9, the rest 3; the 16,000-step candidate, 2026-12-03). The
# service tests skip the goldens (pinned to the shipped model; re-pin them with
# `python tests/service/golden_testkit.py` once the candidate ships). Labels are read only by the
# measurements, as everywhere.
set -uo pipefail

PYTHON=${PYTHON:-python}
DATA=${DATA:-data/processed}
RUN=${RUN:?set RUN to the candidate run folder}
LOSO_RUN=${LOSO_RUN:-}
EXP=${EXP:-$RUN-exported}
LOSO_EXP=${LOSO_EXP:-$LOSO_RUN-exported}
CLI="$PYTHON -m training"   # the complementme command, as shipped.sh runs it

step() {  # name, command...: run one measurement, keep going on failure, say which failed
    local name=$1
    shift
    echo "== $name: $*"
    if "$@"; then echo "== $name: done"; else echo "== $name: FAILED ($?)"; failed+=("$name"); fi
}
failed=()

[ -f "$EXP/manifest.json" ] || step export "$PYTHON" -m training export --run "$RUN" --out "$EXP"
# The fixed-embedding baseline starts from the weights committed beside the benchmark, copied, so
# its rows are the shipped report's (retrained, they differ by host); data of another hash trains
# its own, under the candidate's folder.
mkdir -p "$EXP/benchmark" && cp docs/benchmark/eval_fixed_embedding-*.pt "$EXP/benchmark/"
step benchmark $CLI evaluate --threads 1 --artifacts "$EXP" --run "$RUN" --data "$DATA" \
    --methods random,ck10,fixed,likelihood,ranked,ours --no-progress --notes docs/benchmark-notes.md \
    --fixed-cache "$EXP/benchmark" --out "$EXP/benchmark" --report "$EXP/benchmark/benchmark.md"
if [ -n "$LOSO_RUN" ]; then
    [ -f "$LOSO_EXP/manifest.json" ] || step loso-export "$PYTHON" -m training export --run "$LOSO_RUN" \
        --out "$LOSO_EXP"
    step loso-benchmark $CLI evaluate --threads 1 --artifacts "$LOSO_EXP" --run "$LOSO_RUN" --data "$DATA" \
        --methods ck10,ours --no-progress --out "$LOSO_EXP/benchmark" --report "$LOSO_EXP/benchmark/benchmark.md"
fi
step assembly $CLI evaluate-assembly --artifacts "$EXP" --no-report --out "$EXP/assembly" --no-progress
step frames $CLI evaluate-frames --artifacts "$EXP" --out "$EXP/frame-fit"
REAL=${REAL:-data/real-test/processed}
if [ -f "$REAL/dataset.json" ]; then
    step real $CLI evaluate-real --data "$REAL" --artifacts "$EXP" --out "$EXP/real"
fi
step service-tests env COMPLEMENTME_TEST_ARTIFACTS="$EXP" "$PYTHON" -m pytest -q -p no:cacheprovider \
    tests/service --deselect tests/service/test_golden.py

echo "results: $EXP/benchmark/benchmark.md, $EXP/assembly/results.json, $EXP/frame-fit/results.json," \
     "$EXP/real/results.json (against docs/benchmark-real/results.json)"
[ -n "$LOSO_RUN" ] && echo "leave-one-style-out: $LOSO_EXP/benchmark/benchmark.md"
if [ ${#failed[@]} -gt 0 ]; then
    echo "failed: ${failed[*]}" >&2
    exit 1
fi

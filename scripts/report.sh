#!/usr/bin/env bash
# Makes docs/results.md and its data in docs/report/ (report.json, Fig. 7's SVG files) again: the
# paper's Tables 2-6 and Fig. 7 on the twin with the bundled policies in policies/. About an hour
# on 2 cores. `celld report --from docs/report/report.json` makes the page again from the saved
# data alone, in a second.
#
# Fig. 7's three learning curves come from three training runs under runs/report/ (ignored by
# git; removed and made afresh each time):
#   T27   `celld train td3 --seed 2027` with the default TD3 settings (trust region 0.002,
#         exploration noise 0.002) in a run directory whose lstm.safetensors is the bundled
#         policy: BC+TD3 in the hierarchy
#   NB27  the same with --no-bc-init: TD3 in the hierarchy from fresh actors
#   SW30  `celld train td3 --seed 2030 --robots 10 --td3-step-size
#         --td3-step-fine-trust-region 0.6` from policies/swift-bc:
#         BC+TD3 with the step-size agent, the run that makes policies/swift.safetensors
#   flat  `celld train flat --seed 2026 --demonstrator expert`: the flat TD3 baseline, the run
#         that makes policies/td3.safetensors (scripts/bundled-policies.sh)
# Then `celld report` evaluates every table cell on 1000 episodes (evaluation seed 1) and keeps
# the curves in report.json.
# Everything is seeded: on the same code and policies the tables and curves come out the same
# (report.json's wall_s figures are timings and differ).
#
# Run it from anywhere inside the repository:  scripts/report.sh
source "$(dirname "$0")/common.sh"
RUNS=runs/report
total=$SECONDS

rm -rf "$RUNS"
mkdir -p "$RUNS/T27" "$RUNS/NB27" "$RUNS/SW30"
cp policies/default.safetensors "$RUNS/T27/lstm.safetensors"
cp policies/default.safetensors "$RUNS/NB27/lstm.safetensors"
cp policies/swift-bc.safetensors "$RUNS/SW30/lstm.safetensors"

# The two TD3 runs side by side, one thread each; then the flat baseline.
step td3-bc-init env RAYON_NUM_THREADS=1 "$CELLD" train td3 --out "$RUNS/T27" --seed 2027 &
first=$!
step td3-no-bc-init env RAYON_NUM_THREADS=1 "$CELLD" train td3 --no-bc-init --out "$RUNS/NB27" --seed 2027 &
second=$!
wait "$first"
wait "$second"
step td3-step-size env RAYON_NUM_THREADS=1 "$CELLD" train td3 --out "$RUNS/SW30" --seed 2030 \
    --robots 10 --td3-step-size --td3-step-fine-trust-region 0.6
step td3-flat env RAYON_NUM_THREADS=1 "$CELLD" train flat --out "$RUNS/flat" --seed 2026 --demonstrator expert

step report "$CELLD" report --episodes 1000 --out docs/report --page docs/results.md \
    --made-by scripts/report.sh \
    --curve "BC+TD3 (hierarchical)=$RUNS/T27/td3_curve.json" \
    --curve "TD3 without BC (hierarchical)=$RUNS/NB27/td3_curve.json" \
    --curve "TD3, one 6-DoF actor (td3)=$RUNS/flat/td3-flat_curve.json" \
    --curve "BC+TD3 with the step-size agent (hierarchical-swift-reference)=$RUNS/SW30/td3_curve.json"

echo "== all done in $((SECONDS - total)) s; git diff docs/results.md docs/report shows what changed"

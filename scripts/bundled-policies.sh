#!/usr/bin/env bash
# Makes the six bundled policies again:
#   policies/default.safetensors  the hierarchical policy of the reference cell
#                                 (controller `hierarchical-reference`)
#   policies/bc.safetensors       plain behaviour cloning (controller `bc`)
#   policies/td3.safetensors      the flat TD3 baseline (controller `td3`)
#   policies/across-cells.safetensors  the policy trained across randomised cells
#                                 (controller `hierarchical-cells`)
#   policies/swift.safetensors    the fast hierarchical policy of the reference cell, learnt from
#                                 expert-swift and refined by TD3 (controller `hierarchical-swift-reference`)
#   policies/swift-bc.safetensors its policy before TD3 (the start of the TD3 run)
#   policies/swift-cells.safetensors  the fast policy trained across randomised cells, the
#                                 default (controller `hierarchical-swift-cells`)
#
# Every flag and seed below is the one the committed files were made with; the runs that set
# RAYON_NUM_THREADS=1 did so then too. Every committed file is today's code's: these commands
# write each byte for byte (decisions 0049, 0050 and 0051). The run directories go to
# runs/bundled/ (ignored by git); a stage refuses to overwrite an earlier run's output, so
# delete runs/bundled to start over.
#
# It takes about an hour and three quarters of CPU (docs/learning-reference.md § The bundled policies, and the
# records it links, have the runs' times).
# Run it from anywhere inside the repository:  scripts/bundled-policies.sh
source "$(dirname "$0")/common.sh"
RUNS=runs/bundled
mkdir -p "$RUNS"
total=$SECONDS

# hierarchical-reference 1: behaviour cloning on 800 demonstrations of expert-careful, the sideways errors
# in the bore weighted 30 in the BC loss; the TD3 stage runs one episode
step hierarchical-reference-1 "$CELLD" train all --out "$RUNS/W30" --seed 2026 --demonstrator expert-careful \
    --bc-bore-lateral-weight 30 --td3-episodes 1

# hierarchical-reference 2: DAgger, that policy drives 800 episodes and the demonstrator labels them
step hierarchical-reference-2 "$CELLD" train all --out "$RUNS/W30r1" --seed 2026 --demonstrator expert-careful \
    --bc-bore-lateral-weight 30 --dagger-policy "$RUNS/W30/policy.safetensors" \
    --bc-epochs 100 --lstm-epochs 30 --td3-episodes 1

# hierarchical-reference 3: fine-tuning: start from the last policy, add 800 episodes of it, BC at 0.002
# for 6 epochs (the last 3 at 0.0005), the selector at 5e-4
FT=(--bc-lr 0.002 --bc-epochs 6 --bc-anneal-fraction 0.5 --bc-anneal-factor 0.25
    --bc-orientation-epochs 100 --lstm-lr 5e-4 --lstm-epochs 10 --td3-episodes 1)
step hierarchical-reference-3 env RAYON_NUM_THREADS=1 "$CELLD" train all --out "$RUNS/W30ft" --seed 2027 \
    --demonstrator expert-careful "${FT[@]}" --bc-bore-lateral-weight 30 \
    --init-policy "$RUNS/W30r1/policy.safetensors" --dagger-policy "$RUNS/W30r1/policy.safetensors"
cp "$RUNS/W30ft/policy.safetensors" policies/default.safetensors

# hierarchical-cells: `celld train policy` on expert-careful's demonstrations (the default
# until decision 0048), one command: behaviour cloning on 1600 demonstrations, each on a cell of its own drawn over the ranges the
# product is specified for, the policy reading cell-scaled inputs (a version 2 file), the
# sideways errors in the bore weighted 30, the orientation errors counted relative to their
# labels down to 0.2, the TD3 stage one episode (round-0, and no DAgger round by default);
# then the polishing round from it, the position actor's errors relative to their labels down
# to 0.3, 6 epochs at 0.002, then 500 TD3 episodes that also refine the selector's step size on
# 10 kept robots (polish)
step hierarchical-cells "$CELLD" train policy --out "$RUNS/across-cells" --seed 2026 \
    -- --demonstrator expert-careful
cp "$RUNS/across-cells/policy.safetensors" policies/across-cells.safetensors

# hierarchical-swift-cells: `celld train policy` with its defaults, the same one command on
# expert-swift's demonstrations (no holds, steps up to the 5 mm limit)
step hierarchical-swift-cells "$CELLD" train policy --out "$RUNS/swift-across-cells" --seed 2026
cp "$RUNS/swift-across-cells/policy.safetensors" policies/swift-cells.safetensors

# hierarchical-swift-reference 1: behaviour cloning on 800 demonstrations of expert-swift (no holds,
# steps up to the 5 mm limit), the sideways errors in the bore weighted 30
step hierarchical-swift-reference-1 "$CELLD" train all --out "$RUNS/S30" --seed 2026 --demonstrator expert-swift \
    --bc-bore-lateral-weight 30 --td3-episodes 1

# hierarchical-swift-reference 2: DAgger, that policy drives 800 episodes and the demonstrator labels them
# (seed 2027: the better of the two seeds tried for this round;
# docs/experiments/2026-11-26-0087bca-a-fast-policy-and-kept-robots.md has both)
step hierarchical-swift-reference-2 "$CELLD" train all --out "$RUNS/S30r1" --seed 2027 --demonstrator expert-swift \
    --bc-bore-lateral-weight 30 --dagger-policy "$RUNS/S30/policy.safetensors" \
    --bc-epochs 100 --lstm-epochs 30 --td3-episodes 1
cp "$RUNS/S30r1/policy.safetensors" policies/swift-bc.safetensors

# hierarchical-swift-reference 3: TD3 with the step-size agent from that policy: the selector's step
# size on the approach learns from the twin, and near the entrance and in the bore it may
# move 0.6 from its start (0.2 fewer steps than the default 0.3 on average over five TD3
# seeds, decision 0032); the best
# of the validations every 50 episodes is kept (seed 2030: from the swift-bc of its day, of the
# five seeds tried under decision 0035, 2027-2031, the one whose kept validation took the
# fewest steps, as again under decision 0038;
# docs/experiments/2026-12-02-3f53f0e-centring-in-the-bore-beyond-the-bound.md has all five)
mkdir -p "$RUNS/S30r1-td3"
cp policies/swift-bc.safetensors "$RUNS/S30r1-td3/lstm.safetensors"
step hierarchical-swift-reference-3 env RAYON_NUM_THREADS=1 "$CELLD" train td3 --out "$RUNS/S30r1-td3" \
    --seed 2030 --robots 10 --td3-step-size --td3-step-fine-trust-region 0.6
cp "$RUNS/S30r1-td3/policy.safetensors" policies/swift.safetensors

# bc: plain behaviour cloning on 800 demonstrations of expert-state-only (the default
# demonstrator), BC at a constant rate; its BC policy is the `bc` baseline
step bc env RAYON_NUM_THREADS=1 "$CELLD" train all --out "$RUNS/bcrun" --seed 2026 --bc-anneal-fraction 0
cp "$RUNS/bcrun/bc-policy.safetensors" policies/bc.safetensors

# td3: the flat TD3 baseline (one 6-DoF actor, no BC, no hierarchy)
step td3 env RAYON_NUM_THREADS=1 "$CELLD" train flat --out "$RUNS/flat" --seed 2026 --demonstrator expert
cp "$RUNS/flat/td3-flat-policy.safetensors" policies/td3.safetensors

echo "== all done in $((SECONDS - total)) s; git status policies/ shows whether any file changed"
sha256sum policies/default.safetensors policies/bc.safetensors policies/td3.safetensors \
    policies/across-cells.safetensors policies/swift-bc.safetensors policies/swift.safetensors \
    policies/swift-cells.safetensors

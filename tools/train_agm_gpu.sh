#!/usr/bin/env bash
# Train the AGM on one GPU inside a fixed wall-time budget, in calls that each render their own synthetic data.
#
#   tools/train_agm_gpu.sh MODELS WORK BUDGET_S CALLS "SEED:SCENES ..." [RESUME_DIR]
#
# MODELS: the BOP models folder; WORK: scratch folder; BUDGET_S: seconds this call may take in all; CALLS: how
# many such calls the run is planned over; the seeds: `axispose synth` datasets to render first (20 images per
# scene, all CPU cores). A first call (no RESUME_DIR) trains 30 s with the recipe's step count left open,
# measures steps per second, fixes `steps` so the cosine schedule ends after CALLS calls of this length, and
# goes on (a resume with a new `steps`, which the trainer allows). A later call resumes from RESUME_DIR
# (train.yaml, agm.csv, agm.safetensors.state.pt.*, the state split in parts). The run ends up in WORK/run.
# CONFIG (default config/train_agm_gpu.yaml) and DEVICE (default cuda) may be set in the environment.
set -euo pipefail
models=$1 work=$2 budget=$3 calls=$4 seeds=$5 resume=${6:-}
config=${CONFIG:-config/train_agm_gpu.yaml} device=${DEVICE:-cuda}
start=$SECONDS
ax="python3 -m axispose_core.cli"
run=$work/run
mkdir -p "$run"
data=()
for spec in $seeds; do
    $ax synth --models "$models" --out "$work/synth$spec" --scenes "${spec#*:}" --images-per-scene 20 \
        --seed "${spec%:*}" --workers "$(nproc)"
    data+=("$work/synth$spec")
done
$ax synth --models "$models" --out "$work/val" --scenes 5 --images-per-scene 20 --seed 1000 --workers "$(nproc)"
echo "synthetic data: $((SECONDS - start)) s"
train() {  # $1: config, $2: minutes
    $ax train --data "${data[@]}" --val "$work/val" --out "$run/agm.safetensors" --config "$1" --max-minutes "$2" \
        --device "$device" --threads 4 ${resume_arg:+--resume "$run/agm.safetensors.state.pt"}
}
if [[ -z $resume ]]; then
    resume_arg=
    sed 's/^steps:.*/steps: 1000000/' "$config" >"$work/probe.yaml"
    train "$work/probe.yaml" 0.5
    resume_arg=1
    left=$((budget - (SECONDS - start) - 60))
    python3 - "$run/agm.csv" "$left" "$calls" "$work/train.yaml" "$config" <<'EOF'
import csv, re, sys
rows = [r for r in csv.DictReader(open(sys.argv[1])) if r["step"]]
a, b = rows[len(rows) // 3], rows[-1]
rate = (int(b["step"]) - int(a["step"])) / (float(b["seconds"]) - float(a["seconds"]))
steps = int(rate * (int(sys.argv[2]) + 30) * int(sys.argv[3]))
text = re.sub(r"(?m)^steps:.*$", f"steps: {steps}", open(sys.argv[5]).read())
open(sys.argv[4], "w").write(text)
print(f"{rate:.2f} steps/s -> steps: {steps}")
EOF
else
    resume_arg=1
    cp "$resume/train.yaml" "$resume/agm.csv" "$run/"
    cat "$resume"/agm.safetensors.state.pt.* >"$run/agm.safetensors.state.pt"
    cp "$resume/train.yaml" "$work/train.yaml"
fi
left=$((budget - (SECONDS - start) - 45))
train "$work/train.yaml" "$(python3 -c "print($left / 60)")"
echo "total: $((SECONDS - start)) s"

#!/usr/bin/env bash
# Train the AGM (or the localiser) on one GPU inside a fixed wall-time budget, in calls that each render their own
# synthetic data.
#
#   tools/train_gpu.sh MODELS WORK BUDGET_S CALLS "SEED:SCENES ..." [RESUME_DIR]
#
# MODELS: the BOP models folder; WORK: scratch folder; BUDGET_S: seconds this call may take in all; CALLS: how
# many such calls the run is planned over; the seeds: `axispose synth` datasets to render first (20 images per
# scene, all CPU cores). A first call (no RESUME_DIR) trains PROBE_MINUTES with the step count left open,
# measures steps per second, fixes `steps` so that the cosine schedule ends after CALLS calls like this one, and
# goes on (a resume with a new `steps`, which the trainers allow). A later call resumes from RESUME_DIR: the
# previous call's train.yaml, NAME.csv and NAME.safetensors.state.pt (whole, or split into parts named
# NAME.safetensors.state.pt.00, .01, ...), NAME being agm or localiser. The run ends up in WORK/run, the planned
# config in WORK/train.yaml.
# `axispose synth` renders only the scenes a folder lacks, so a later call on a machine still warm, given the same
# WORK, starts training at once; a new WORK renders everything again.
#
# Environment: TRAINER (train: the AGM, default; train-detector: the localiser), CONFIG (default
# config/train_agm_gpu.yaml or config/train_detector_gpu.yaml), DEVICE (cuda), PROBE_MINUTES (0.5), VAL_SCENES (5
# held-out scenes, seed 1000, for the trainer's validation), RESERVE_S (45: seconds left free at the end), PYTHON
# (python3: the interpreter with axispose_core's requirements), INIT (a checkpoint for the first call to start
# from, e.g. the shipped model: the trainer's --init; later calls resume, and their checkpoints still name it),
# EXPORT (a folder, e.g. the device's $OUT, that gets what a later call's RESUME_DIR needs and the checkpoint:
# train.yaml, NAME.csv, NAME.safetensors and the resume state split into 15 MB parts, since files larger than
# 16 MiB do not come back from the device).
set -euo pipefail
models=$1 work=$2 budget=$3 calls=$4 seeds=$5 resume=${6:-}
trainer=${TRAINER:-train}
case $trainer in
    train) name=agm default_config=config/train_agm_gpu.yaml ;;
    train-detector) name=localiser default_config=config/train_detector_gpu.yaml ;;
    *)
        echo "train_gpu.sh: TRAINER is train (the AGM) or train-detector (the localiser), not '$trainer'" >&2
        exit 1
        ;;
esac
config=${CONFIG:-$default_config} device=${DEVICE:-cuda} probe=${PROBE_MINUTES:-0.5}
reserve=${RESERVE_S:-45}
if ((budget <= reserve)); then
    echo "train_gpu.sh: a budget of $budget s leaves no time to train after the $reserve s kept free (RESERVE_S)" >&2
    exit 1
fi
start=$SECONDS
py=${PYTHON:-python3}
ax="$py -m axispose_core.cli"
run=$work/run
mkdir -p "$run"
data=()
for spec in $seeds; do
    $ax synth --models "$models" --out "$work/synth$spec" --scenes "${spec#*:}" --images-per-scene 20 \
        --seed "${spec%:*}" --workers "$(nproc)"
    data+=("$work/synth$spec")
done
$ax synth --models "$models" --out "$work/val" --scenes "${VAL_SCENES:-5}" --images-per-scene 20 --seed 1000 \
    --workers "$(nproc)"
echo "synthetic data: $((SECONDS - start)) s"
train() {  # $1: config, $2: seconds
    if (($2 <= 0)); then
        echo "train_gpu.sh: no time left to train (budget $budget s, $((SECONDS - start)) s used)" >&2
        exit 1
    fi
    local start_from=()  # the run's own state once there is one, else INIT's weights (if given)
    if [[ -n $resume_arg ]]; then
        start_from=(--resume "$run/$name.safetensors.state.pt")
    elif [[ -n ${INIT:-} ]]; then
        start_from=(--init "$INIT")
    fi
    $ax "$trainer" --data "${data[@]}" --val "$work/val" --out "$run/$name.safetensors" --config "$1" \
        --max-minutes "$($py -c "print($2 / 60)")" --device "$device" --threads 4 "${start_from[@]}"
}
if [[ -z $resume ]]; then
    resume_arg=
    sed 's/^steps:.*/steps: 1000000/' "$config" >"$work/probe.yaml"
    probe_start=$SECONDS
    train "$work/probe.yaml" "$($py -c "print(round($probe * 60))")"
    resume_arg=1
    # a later call trains for about what this one has left plus the probe's time (it renders instead of probing)
    per_call=$((budget - (SECONDS - start) - reserve + SECONDS - probe_start))
    $py - "$run/$name.csv" "$per_call" "$calls" "$config" "$work/train.yaml" <<'PY'
import csv, re, sys
rows = [r for r in csv.DictReader(open(sys.argv[1])) if r["step"]]
if len(rows) < 3:
    sys.exit(f"train_gpu.sh: the probe logged {len(rows)} rows (one per 10 steps); give it more PROBE_MINUTES")
a, b = rows[len(rows) // 3], rows[-1]
rate = (int(b["step"]) - int(a["step"])) / (float(b["seconds"]) - float(a["seconds"]))
steps = int(rate * int(sys.argv[2]) * int(sys.argv[3]))
open(sys.argv[5], "w").write(re.sub(r"(?m)^steps:.*$", f"steps: {steps}", open(sys.argv[4]).read()))
print(f"{rate:.2f} steps/s -> steps: {steps}")
PY
else
    resume_arg=1
    cp "$resume/train.yaml" "$resume/$name.csv" "$run/"
    if [[ -f $resume/$name.safetensors.state.pt ]]; then
        cp "$resume/$name.safetensors.state.pt" "$run/"
    else
        cat "$resume/$name".safetensors.state.pt.* >"$run/$name.safetensors.state.pt"
    fi
    cp "$resume/train.yaml" "$work/train.yaml"
fi
train "$work/train.yaml" $((budget - (SECONDS - start) - reserve))
if [[ -n ${EXPORT:-} ]]; then
    mkdir -p "$EXPORT"
    cp "$work/train.yaml" "$run/$name.csv" "$run/$name.safetensors" "$EXPORT/"
    split -b 15M -d "$run/$name.safetensors.state.pt" "$EXPORT/$name.safetensors.state.pt."
fi
echo "total: $((SECONDS - start)) s"

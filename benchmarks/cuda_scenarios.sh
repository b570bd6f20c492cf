#!/usr/bin/env bash
# Every shipped scenario with --device cuda (masked and tied estimators, the change detector, a NumPy function,
# float32 included), each in its own process, all at once on one GPU.
#
#     [DEVICE=cpu] [STEPS=N] [JOBS=J] benchmarks/cuda_scenarios.sh OUT [SECONDS]
#
# rcotorch must be installed (the `rcotorch` command on PATH); the Silverbox run reads $RCOTORCH_SILVERBOX.
# Each run writes OUT/TAG/ (summary.json, rcotorch.log, figures, TensorBoard) and OUT/TAG.log (its terminal
# output, exit code and wall time). SECONDS (default 420) bounds each run. STEPS shortens every run to N steps
# (the thermosphere's to N / 50; the building's change then comes at N / 400 s); without it each scenario runs
# its own length (the Silverbox's 65,062 steps and its replays of the test sets take about 5 minutes on one GPU
# alone, far longer while a dozen processes share it). DEVICE=cpu gives the references that
# benchmarks/cuda_compare.py reads beside them; JOBS bounds the runs at once (default: all).
set -u
out=${1:?usage: cuda_scenarios.sh OUT [SECONDS]}
limit=${2:-420}
device=${DEVICE:-cuda}
steps=${STEPS:-}
jobs=${JOBS:-100}
mkdir -p "$out"

one() {
    local tag=$1
    shift
    while [ "$(jobs -rp | wc -l)" -ge "$jobs" ]; do sleep 0.2; done
    (
        start=$(date +%s%N)
        timeout -k 10 "$limit" rcotorch run "$@" --device "$device" --quiet --out "$out/$tag" > "$out/$tag.log" 2>&1
        rc=$?
        echo "rc=$rc wall_ms=$(( ($(date +%s%N) - start) / 1000000 ))" >> "$out/$tag.log"
    ) &
}

short=()
thermo=(--steps 240)
building=()
silverbox=()
if [ -n "$steps" ]; then
    short=(--steps "$steps")
    thermo=(--steps $(( steps / 50 > 20 ? steps / 50 : 20 )))
    building=(--set t_change=$(( steps / 400 )) --set warmup=100 --set window=100 --set holdoff=300)
    silverbox=(--set test_sets=false --set val_stop=107712)
fi

one sk          sdof-stiffness "${short[@]}"
one skd_b64     sdof-stiffness-damping --batch 64 "${short[@]}"
one skd_f32     sdof-stiffness-damping --batch 8 --dtype float32 "${short[@]}"
one imp         sdof-dynamic-impedance "${short[@]}"
one two_b16     twodof-stiffness --batch 16 "${short[@]}"                          # masked static gain
one rlc         rlc-circuit "${short[@]}"
one friction    mass-friction --batch 16 "${short[@]}"                             # a NumPy function in the truth
one building    shear-building-damage --batch 200 "${short[@]}" "${building[@]}"   # change detector, restarts
one silverbox   silverbox-cubic-stiffness "${short[@]}" "${silverbox[@]}"          # real data, basis all
one th          thermosphere-no-cooling "${thermo[@]}" --set replay=false
one th_tied     thermosphere-no-cooling "${thermo[@]}" --set structure=temperature --set shared=true   # tied
one th_err      thermosphere-no-cooling "${thermo[@]}" --set structure=error --set replay=false
wait

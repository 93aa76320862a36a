#!/bin/bash
# Issue 26's validation runs at full size on a machine of 4 GPUs, one call: every job under one deadline, the
# results, logs and checkpoints packed into $OUT/issue26.tgz (a call brings back at most 8 files).
#   bash benchmarks/issue26_gpu.sh [RESUME_DIR]     # on the GPU machine, from the repository root, polydem installed
# RESUME_DIR: a folder of the tapping checkpoints (*.npz) and JSON of the previous call (carried back): the tap runs
# go on from there (tapping.py --resume), so that taps to saturation take several calls.
# BUDGET (seconds, default 510) bounds the jobs; taps and Beverloo write their JSON as they go, Janssen at its end.
set -u
W=/tmp/w26; rm -rf $W; mkdir -p $W/res $W/log; END=$((SECONDS + ${BUDGET:-510}))
# never 0 or less: `timeout 0` means no limit at all, and a job started late would outlive the call
left() { local l=$((END - SECONDS)); [ $l -lt 5 ] && l=5; echo $l; }
R=${1:-}
gpu() { CUDA_VISIBLE_DEVICES=$1 timeout $(left) "${@:2}"; }
tapjob() {  # GPU NAME ARGS...: a tap run that stops a minute before the deadline (its clock starts before the build) and keeps a checkpoint
  local g=$1 name=$2; shift 2
  local resume=()
  [ -n "$R" ] && [ -f "$R/$name.npz" ] && resume=(--resume "$R/$name.npz")
  gpu $g python benchmarks/validation/tapping.py --device cuda:0 --taps 400 --start 1.0 --period 0.2 --coordination \
    --stop-after $(( $(left) - 60 )) "${resume[@]}" --out $W/res/$name.json "$@" > $W/log/$name.log 2>&1
}
# GPU 0, 1: taps to saturation, cubes (two seeds) and tetrahedra
tapjob 0 tap_cube_s1 --grains 5000 --width 24 --seed 1 &
tapjob 0 tap_tetra_s1 --shape tetrahedron --grains 8000 --width 14 --seed 1 &
tapjob 1 tap_cube_s2 --grains 5000 --width 24 --seed 2 &
# GPU 1: Janssen with a fill in batches, the floor lowered 0.2 and 0.5 d
for lw in 0.2 0.5; do
  gpu 1 python benchmarks/validation/janssen.py --device cuda:0 --size full --stages 4 --fill-time 1.0 --max-time 1.0 --lower $lw \
    --out $W/res/janssen_full_staged_lower$lw.json > $W/log/janssen_$lw.log 2>&1 &
done
# GPU 2, 3: Beverloo, a third seed and 14 d
for gso in "2|3|12,9" "2|3|10,8" "3|1|14" "3|2|14"; do
  IFS='|' read g s o <<< "$gso"
  gpu $g python benchmarks/validation/beverloo.py --size full --device cuda:0 --seeds 1 --first-seed $s --orifices $o \
    --tag full_s$s --out $W/res/beverloo_full_s${s}_${o//,/-}.json > $W/log/beverloo_s${s}_${o//,/-}.log 2>&1 &
done
# A hard deadline: whatever still runs is stopped, so that the results are packed before the call's limit.
while [ $SECONDS -lt $END ] && [ -n "$(jobs -r)" ]; do sleep 2; done
pkill -9 -f "python.*benchmarks/validation"; sleep 1
tar czf ${OUT:-.}/issue26.tgz -C $W .
cd $W/log && for f in *.log; do echo "== $f"; grep -v "^Module\|^Warp\|^   \|^$" $f | tail -3 | cut -c1-200; done

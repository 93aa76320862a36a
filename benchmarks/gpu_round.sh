#!/bin/bash
# The measurements still open, on a machine of 4 GPUs in one call (kind nvidia-h100-x4), under one hard deadline:
# whatever still runs at BUDGET seconds (default 500) is stopped, and everything is packed into $OUT/round.tgz
# (res/: JSON and tap checkpoints, log/: one log a job). From the repository root, polydem importable.
#   BUDGET=500 bash benchmarks/gpu_round.sh
# GPU 0: the USD frame's host memory at 1e7 bodies (benchmarks/usd_frame_memory.py), then the CUDA test files
#        the last changes touch (the USD tests run where usd-core is installed).
# GPU 1: the tap runs, each resumed from its latest checkpoint in benchmarks/results/validation/taps/.
# GPU 2: issue 27's pair-thread order on the mixed pile with contacts, alone (timings).
# GPU 3: tetrahedra's loosest packing (friction annealing at mu_fill = 1), Beverloo's third seed at 10 and 8 d.
set -u
# Its own process group, so that the deadline stops exactly this script's jobs (never the caller's shell).
[ -z "${GPU_ROUND_LEADER:-}" ] && GPU_ROUND_LEADER=1 exec setsid --wait bash "$0" "$@"
cd "$(dirname "$0")/.."
W=/tmp/round; rm -rf $W; mkdir -p $W/res $W/log; END=$((SECONDS + ${BUDGET:-500}))
# never 0 or less: `timeout 0` means no limit at all
left() { local l=$((END - SECONDS)); [ $l -lt 5 ] && l=5; echo $l; }
gpu() { CUDA_VISIBLE_DEVICES=$1 timeout $(left) "${@:2}"; }
TAPS=benchmarks/results/validation/taps
latest() { ls $TAPS/${1}_t*.npz 2>/dev/null | sort -V | tail -1; }
tapjob() {
  local g=$1 name=$2; shift 2
  local resume=() cp; cp=$(latest $name)
  [ -n "$cp" ] && resume=(--resume "$cp")
  gpu $g python benchmarks/validation/tapping.py --device cuda:0 --taps 400 --start 1.0 --period 0.2 --coordination \
    --stop-after $(( $(left) - 45 )) "${resume[@]}" --out $W/res/$name.json "$@" > $W/log/$name.log 2>&1
}
( gpu 0 python benchmarks/usd_frame_memory.py --device cuda:0 --bodies 10000000 --repeat 1 \
    --out $W/res/usd_frame_memory_h100.json > $W/log/usd_frame_memory.log 2>&1
  CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
    -p no:cacheprovider tests/test_usd.py tests/test_measures.py tests/test_validation_small.py > $W/log/pytest.log 2>&1
) &
tapjob 1 tap_cube_s1 --grains 5000 --width 24 --seed 1 &
tapjob 1 tap_cube_s2 --grains 5000 --width 24 --seed 2 &
tapjob 1 tap_tetra_s1 --shape tetrahedron --grains 8000 --width 14 --seed 1 &
( CUDA_VISIBLE_DEVICES=2 OUT=$W/res timeout $(left) bash benchmarks/issue27_gpu.sh mixed > $W/log/issue27_mixed.log 2>&1 ) &
gpu 3 python benchmarks/validation/anneal.py --device cuda:0 --shape tetrahedron --grains 8000 --width 14 \
  --mu-fill 1.0 --coordination --out $W/res/anneal_tetra_8000_mu1.json > $W/log/anneal_tetra.log 2>&1 &
gpu 3 python benchmarks/validation/beverloo.py --size full --device cuda:0 --seeds 1 --first-seed 3 --orifices 10,8 \
  --tag full_s3 --out $W/res/beverloo_full_s3_10-8.json > $W/log/beverloo_s3_10-8.log 2>&1 &
while [ $SECONDS -lt $END ] && [ -n "$(jobs -r)" ]; do sleep 2; done
# Every process of this session but this shell (timeout puts each job in its own group, not session).
left_over=$(pgrep -s $$ | grep -vx $$); [ -n "$left_over" ] && kill -TERM $left_over 2>/dev/null; sleep 2
left_over=$(pgrep -s $$ | grep -vx $$); [ -n "$left_over" ] && kill -9 $left_over 2>/dev/null; sleep 1
nvidia-smi --query-gpu=name --format=csv > $W/log/gpus.txt 2>&1
tar czf ${OUT:-.}/round.tgz -C $W .
cd $W/log && for f in *.log; do echo "== $f"; grep -v "^Module\|^Warp\|^   \|^$" $f | tail -4 | cut -c1-220; done

#!/bin/bash
# The measurements still open, on a machine of 1, 2 or 4 GPUs in one call, under one hard deadline:
# whatever still runs at BUDGET seconds (default 500) is stopped, and everything is packed into $OUT/round.tgz
# (res/: JSON and tap checkpoints, log/: one log a job). From the repository root, polydem importable.
#   BUDGET=500 bash benchmarks/gpu_round.sh
# On 4 GPUs: GPU 0 builds 1e6 and 1e7 cubes and steps them 20 times, the initial overlaps checked on the host and
# then on the device (benchmarks/build_time.py --overlap-check), with the device memory at the end of each stage;
# GPU 1 builds 7e7 with the device's check (against the 258 s of BENCHMARKS.md 19, the host's check); GPU 2 runs
# the CUDA tests of the files the last changes touch (test_usd.py where usd-core is installed: stage its wheel as a
# part of its own, the GPU bundle has none); the last GPU builds the largest settle pile that fits it with the
# device's check and steps it 20 times (1e8 cubes on a card of more than 100 GB, an H200; else 4e7).
# On 2 GPUs: GPU 0 runs the CUDA tests and then the 1e6/1e7 builds; GPU 1 the largest pile. On 1: no large pile.
# RUN_TAPS=1 runs the tap runs instead of GPU 0's job, each resumed from its latest checkpoint in
# benchmarks/results/validation/taps/ (issue 26).
set -u
# Its own process group, so that the deadline stops exactly this script's jobs (never the caller's shell).
[ -z "${GPU_ROUND_LEADER:-}" ] && GPU_ROUND_LEADER=1 exec setsid --wait bash "$0" "$@"
cd "$(dirname "$0")/.."
W=/tmp/round; rm -rf $W; mkdir -p $W/res $W/log /tmp/pours; END=$((SECONDS + ${BUDGET:-500}))
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
NGPU=$(nvidia-smi --query-gpu=index --format=csv,noheader | wc -l)
# the CUDA tests first (they decide whether the device check may be trusted), then the build on the host and device
# checks at 1e6 and 1e7
cuda_tests() {
  CUDA_VISIBLE_DEVICES=$1 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
    -p no:cacheprovider tests/test_overlap_check.py tests/test_usd.py tests/test_pair_order.py tests/test_memory.py \
    > $W/log/pytest.log 2>&1
}
small_builds() {
  for oc in host device; do
    gpu $1 python benchmarks/build_time.py --device cuda:0 --sizes 1e6,1e7 --steps 20 --no-git --overlap-check $oc \
      --out $W/res/build_time_settle_$oc.json > $W/log/build_time_$oc.log 2>&1
  done
}
# the largest pile that fits the last card: 1e8 cubes on a card of more than 100 GB (an H200), else 4e7
last=$((NGPU - 1))
big=$(nvidia-smi --query-gpu=memory.total --format=csv,noheader,nounits -i $last \
  | awk '{print ($1 > 100000) ? 100000000 : 40000000}')
big_build() {
  gpu $last python benchmarks/build_time.py --device cuda:0 --sizes $big --steps 20 --no-git --overlap-check device \
    --out $W/res/build_time_settle_$big.json > $W/log/build_big.log 2>&1
}
# MODE=grouping: the pair threads grouped by cost against by cost and contact, the mixed pile (GPU 0) and the cube
# pile (GPU 1, then the largest pile's build), benchmarks/issue27_gpu.sh mixed
grouping() {
  ( cd $W/res && mkdir -p grouping )
  ( CUDA_VISIBLE_DEVICES=0 OUT=$W/res/grouping SIZES=100000 ORDERS="cost contact" CUBE_ORDERS="" \
      timeout $(left) bash benchmarks/issue27_gpu.sh mixed > $W/log/grouping_mixed_1e5.log 2>&1
    CUDA_VISIBLE_DEVICES=0 OUT=$W/res/grouping SIZES=10000 ORDERS="cost contact" CUBE_ORDERS="default contact" \
      timeout $(left) bash benchmarks/issue27_gpu.sh mixed > $W/log/grouping_1e4.log 2>&1 ) &
  ( CUDA_VISIBLE_DEVICES=1 OUT=$W/res/grouping SIZES=100000 ORDERS="" CUBE_ORDERS="default contact" \
      timeout $(left) bash benchmarks/issue27_gpu.sh mixed > $W/log/grouping_cubes_1e5.log 2>&1
    big_build ) &
}
# MODE=grouping2: the same with the costliest pairs first ("contact"), the mixed pile at 1e5 on GPU 0 and the rest
# on GPU 1
grouping2() {
  ( cd $W/res && mkdir -p grouping )
  ( CUDA_VISIBLE_DEVICES=0 OUT=$W/res/grouping SIZES=100000 ORDERS="cost contact" CUBE_ORDERS="" \
      timeout $(left) bash benchmarks/issue27_gpu.sh mixed > $W/log/grouping_mixed_1e5.log 2>&1
    CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
      -p no:cacheprovider tests/test_pair_order.py > $W/log/pytest.log 2>&1 ) &
  ( CUDA_VISIBLE_DEVICES=1 OUT=$W/res/grouping SIZES="10000 100000" ORDERS="" CUBE_ORDERS="default contact" \
      timeout $(left) bash benchmarks/issue27_gpu.sh mixed > $W/log/grouping_cubes.log 2>&1
    CUDA_VISIBLE_DEVICES=1 OUT=$W/res/grouping SIZES=10000 ORDERS="cost contact cost contact" CUBE_ORDERS="" \
      timeout $(left) bash benchmarks/issue27_gpu.sh mixed > $W/log/grouping_mixed_1e4.log 2>&1 ) &
}
# MODE=grouping1: the same on one GPU, one run after another (the latency-bound mixed pile first)
grouping1() {
  ( cd $W/res && mkdir -p grouping )
  ( for job in "10000|cost contact|" "100000|cost contact|" "10000 100000||default contact"; do
      IFS='|' read -r sizes orders cubes <<< "$job"
      CUDA_VISIBLE_DEVICES=0 OUT=$W/res/grouping SIZES="$sizes" ORDERS="$orders" CUBE_ORDERS="$cubes" \
        timeout $(left) bash benchmarks/issue27_gpu.sh mixed >> $W/log/grouping.log 2>&1
    done
    CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
      -p no:cacheprovider tests/test_pair_order.py > $W/log/pytest.log 2>&1 ) &
}
# MODE=tts: time to a settled pile (time_to_settle.py at 4 dt_rec) with the pair threads in slot order (or by
# cost, the mixed set) and at the default grouping, one after the other on GPU 0: the same piles, bit for bit
tts() {
  ( for job in "1e5 cube slot" "1e5 cube default" "1e4 cube slot" "1e4 cube default" "1e6 cube slot" \
      "1e6 cube default" "1e4 mixed cost" "1e4 mixed default"; do
      read -r n shapes order <<< "$job"
      # --k-rule volume: section 7's piles (the corner rule's stiffer k needs far more steps: the first try of
      # this round ran past its 500 s on 1e5 cubes); -u: a log that shows how far a stopped run got
      gpu 0 python -u benchmarks/time_to_settle.py --device cuda:0 --sizes $n --dt-scales 4 --shapes $shapes \
        --k-rule volume --pair-thread-order $order --out $W/res/tts_${n}_${shapes}_${order}.json \
        >> $W/log/tts.log 2>&1
    done ) &
}
# MODE=tts2: the same piles to section 7's criterion (kinetic energy alone, --speed-fraction off), the orders side by
# side, then 1e5 cubes at the default grouping to the default criterion (section 10c's 226 s, --max-time 3)
tts2() {
  ( for job in "1e4 cube slot" "1e4 cube default" "1e5 cube slot" "1e5 cube default" "1e4 mixed cost" \
      "1e4 mixed default" "1e6 cube default" "1e6 cube slot"; do
      read -r n shapes order <<< "$job"
      gpu 0 python -u benchmarks/time_to_settle.py --device cuda:0 --sizes $n --dt-scales 4 --shapes $shapes \
        --k-rule volume --speed-fraction off --pair-thread-order $order \
        --out $W/res/tts_kinetic_${n}_${shapes}_${order}.json >> $W/log/tts.log 2>&1
    done
    gpu 0 python -u benchmarks/time_to_settle.py --device cuda:0 --sizes 1e5 --dt-scales 4 --k-rule volume \
      --max-time 3 --out $W/res/tts_speed_1e5_cube_default.json >> $W/log/tts.log 2>&1 ) &
}
# MODE=tts3: the damping loads (BENCHMARKS.md 21): the CUDA tests of the change, then the piles at the default
# grouping to section 7's criterion and to the default one (every grain at rest), the largest last
tts3() {
  ( CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
      -p no:cacheprovider tests/test_damping_load.py tests/test_pair_order.py tests/test_memory.py \
      > $W/log/pytest.log 2>&1
    for job in "1e4 cube off 1" "1e5 cube off 1" "1e4 mixed off 1" "1e4 cube default 3" "1e5 cube default 3" \
      "1e6 cube off 1" "1e4 mixed default 3"; do
      read -r n shapes speed tmax <<< "$job"
      sp=(); [ "$speed" = off ] && sp=(--speed-fraction off)
      gpu 0 python -u benchmarks/time_to_settle.py --device cuda:0 --sizes $n --dt-scales 4 --shapes $shapes \
        --k-rule volume "${sp[@]}" --max-time $tmax \
        --out $W/res/tts_damping_${n}_${shapes}_${speed}.json >> $W/log/tts.log 2>&1
    done ) &
}
# the settle step at 1e4 cubes with the previous commit's package (OLD_PKG, on PYTHONPATH) and this one, in turn
fold_pair() {
  for code in old new; do
    pp=(); [ $code = old ] && pp=(env PYTHONPATH=${OLD_PKG:?}:${PYTHONPATH:-})
    "${pp[@]}" python -c "import polydem, polydem.kernels.forces as f; print('$code:', f.__file__)" \
      >> $W/log/settle_fold.log 2>&1
    gpu 0 "${pp[@]}" python -u benchmarks/settle.py --device cuda:0 --sizes 1e4 --precision mixed --k-rule volume \
      --no-graph-compare --steps 400 --out $W/res/settle_1e4_${code}_$1.json >> $W/log/settle_fold.log 2>&1
  done
}
# MODE=mesh: the mesh-wall candidate list and the damping loads written by the gather (BENCHMARKS.md 22): the CUDA
# tests of both, the fine mesh floor's contact cost through the walk and the list side by side (1e4 and 1e5 cubes),
# the settle step at 1e4 cubes before (OLD_PKG: a copy of the previous commit's package, on PYTHONPATH) and after,
# twice each in turn, then 1e5 cubes at 4 dt_rec to the default criterion (every grain at rest), up to 6 s simulated
mesh() {
  ( CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
      -p no:cacheprovider tests/test_damping_load.py "tests/test_meshwall.py::test_candidate_list_gives_the_walks_bits" \
      tests/test_memory.py -k "not redone" > $W/log/pytest.log 2>&1
    for n in 10000 100000; do
      gpu 0 python -u benchmarks/wall_contact_cost.py --device cuda:0 --bodies $n --steps 100 --kinds meshT,pair \
        --triangle-edge 2 --mesh-paths walk,list --out $W/res/wall_contact_cost_fine_$n.json > $W/log/wall_$n.log 2>&1
    done
    fold_pair 1; fold_pair 2
    gpu 0 python -u benchmarks/time_to_settle.py --device cuda:0 --sizes 1e5 --dt-scales 4 --shapes cube \
      --k-rule volume --max-time 6 --out $W/res/tts_rest_1e5_cube.json >> $W/log/tts.log 2>&1 ) &
}
# MODE=mesh2: the candidate list's clipping under the pair kernel's register cap and block size against without
# (OLD_PKG2: the package of the commit before, on PYTHONPATH), each kernel's GPU time; then the fold as in MODE=mesh
mesh2() {
  ( CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
      -p no:cacheprovider "tests/test_meshwall.py::test_candidate_list_gives_the_walks_bits" > $W/log/pytest.log 2>&1
    for n in 10000 100000; do
      gpu 0 env PYTHONPATH=${OLD_PKG2:?}:${PYTHONPATH:-} python -u benchmarks/wall_contact_cost.py --device cuda:0 \
        --bodies $n --steps 100 --kinds meshT,pair --triangle-edge 2 --mesh-paths list \
        --out $W/res/wall_fine_${n}_before.json > $W/log/wall_${n}_before.log 2>&1
      gpu 0 python -u benchmarks/wall_contact_cost.py --device cuda:0 --bodies $n --steps 100 --kinds meshT,pair \
        --triangle-edge 2 --mesh-paths walk,list --profile --out $W/res/wall_fine_$n.json > $W/log/wall_$n.log 2>&1
    done
    fold_pair 1; fold_pair 2 ) &
}
# MODE=mesh3: the one-traversal listing against the two-pass one (OLD_PKG2) and the walk, each kernel's GPU time,
# between the runs of the fold before (OLD_PKG) and after. The set-up and the packing take 30-40 s besides BUDGET:
# in a call of 600 s give BUDGET=540 at most (a call past its limit returns nothing)
mesh3() {
  ( CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
      -p no:cacheprovider "tests/test_meshwall.py::test_candidate_list_gives_the_walks_bits" -k mixed \
      > $W/log/pytest.log 2>&1
    fold_pair 1
    for n in 10000 100000; do
      gpu 0 env PYTHONPATH=${OLD_PKG2:?}:${PYTHONPATH:-} python -u benchmarks/wall_contact_cost.py --device cuda:0 \
        --bodies $n --steps 100 --kinds meshT --triangle-edge 2 --mesh-paths list --profile \
        --out $W/res/wall_fine_${n}_twopass.json > $W/log/wall_${n}_twopass.log 2>&1
      gpu 0 python -u benchmarks/wall_contact_cost.py --device cuda:0 --bodies $n --steps 100 --kinds meshT,pair \
        --triangle-edge 2 --mesh-paths list,walk --profile --out $W/res/wall_fine_$n.json > $W/log/wall_$n.log 2>&1
    done
    fold_pair 2 ) &
}
# MODE=mesh4: a flat patch's cells joined into one (the default) against one cell per triangle, on the fine floor
# (the list and the walk) and in the shipped mesh-wall scenes; the joined cells' test on cuda:0. BUDGET=540 at most.
mesh4() {
  ( CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
      -p no:cacheprovider "tests/test_meshwall.py::test_joined_flat_cells_give_the_triangles_contacts" \
      > $W/log/pytest.log 2>&1
    for n in 10000 100000; do
      gpu 0 python -u benchmarks/wall_contact_cost.py --device cuda:0 --bodies $n --steps 100 --kinds meshT,pair \
        --triangle-edge 2 --mesh-paths list,walk --cells joined,triangles --profile \
        --out $W/res/wall_joined_$n.json > $W/log/wall_joined_$n.log 2>&1
    done
    gpu 0 python -u benchmarks/joined_cells.py --device cuda:0 --warmup 0.5 --out $W/res/joined_cells.json \
      > $W/log/joined_cells.log 2>&1 ) &
}
# MODE=mesh5: the rest of mesh4 (its call ran out): the shipped hopper and cup both ways, the 1e5 floor's joined cells
# against a pair contact. BUDGET=330 in a call with under 450 s of device time left.
mesh5() {
  ( gpu 0 python -u benchmarks/joined_cells.py --device cuda:0 --scenes hopper,tapped_cup --warmup 0.3 --repeats 3 \
      --out $W/res/joined_cells.json > $W/log/joined_cells.log 2>&1
    gpu 0 python -u benchmarks/wall_contact_cost.py --device cuda:0 --bodies 100000 --steps 100 --kinds meshT,pair \
      --triangle-edge 2 --mesh-paths list,walk --cells joined --out $W/res/wall_joined_100000.json \
      > $W/log/wall_joined_100000.log 2>&1 ) &
}
# MODE=conv1: time to a converged pile, polydem's half (benchmarks/converged_pile.py): the pour at k x 1, 4, 16, 64 and
# dt x 4, 1 of the recommended step (each to section 7's criterion), 1e5 cubes first, then 1e4 and 1e3 (several seeds:
# their scatter), then 1e6 at the base setting. BUDGET=530 at most in a call of 600 s.
conv1() {
  ( for job in "1e5 1x4,4x4,16x4,1x1,64x4 0" "1e4 1x4,4x4,16x4,1x1 0,1" "1e3 1x4,4x4,16x4,1x1 0,1,2" "1e6 1x4 0"; do
      read -r n settings seeds <<< "$job"
      gpu 0 python -u benchmarks/converged_pile.py --device cuda:0 --sizes $n --settings $settings --seeds $seeds \
        --k-rule volume --speed-fraction off --max-time 3 --out $W/res/conv_$n.json > $W/log/conv_$n.log 2>&1
    done ) &
}
# MODE=conv4: stiffer piles at larger multiples of their recommended step (which shrinks as 1/k above k x 1, while
# the stable limit shrinks as k^-1/2): 1e4 cubes, two seeds, then 1e5 at k x 16 and 64 near their limits
conv4() {
  ( for job in "1e4 1x4,1x1,4x4,4x8,16x4,16x16,64x16,64x32 0 a" "1e4 1x4,1x1,4x4,4x8,16x4,16x16,64x16,64x32 1 b" \
      "1e4 64x8 0 c" "1e5 16x16 0 d" "1e5 64x32 0 e"; do
      read -r n settings seeds tag <<< "$job"
      gpu 0 python -u benchmarks/converged_pile.py --device cuda:0 --sizes $n --settings $settings --seeds $seeds \
        --k-rule volume --speed-fraction off --max-time 1.5 --out $W/res/conv_${n}_$tag.json > $W/log/conv_${n}_$tag.log 2>&1
    done ) &
}
# MODE=conv5: Newton at 1e4 (1e-3 s down to 1.25e-4 s) and at 1e5 (NEWTON_DTS_1E5, default 5e-4 and 2.5e-4 s)
conv5() {
  ( for n in 10000 100000; do
      dts=${NEWTON_DTS:-1e-3,5e-4,2.5e-4,1.25e-4}; [ $n = 100000 ] && dts=${NEWTON_DTS_1E5:-5e-4,2.5e-4}
      gpu 0 python benchmarks/peers/pour_scene.py export --grains $n --device cuda:0 --out /tmp/pours/pour_$n.json \
        > $W/log/export_$n.log 2>&1
      gpu 0 python -u benchmarks/peers/newton_pour.py --grains $n --device cuda:0 --scene /tmp/pours/pour_$n.json \
        --dt-sweep $dts --max-time 4 --out $W/res/newton_$n.json > $W/log/newton_$n.log 2>&1
    done ) &
}
# MODE=conv6: the pile at steps the toe does not set (1e4 cubes, two seeds): k x 1 below dt_rec (dt study), k x 4 and
# 16 at 1 and 2 x their dt_rec (the k study)
conv6() {
  ( for job in "1x0.5,1x0.25 0,1 a" "4x2,4x1 0,1 b" "16x2 0,1 c" "16x1 0 d" "16x1 1 e"; do
      read -r settings seeds tag <<< "$job"
      gpu 0 python -u benchmarks/converged_pile.py --device cuda:0 --sizes 1e4 --settings $settings --seeds $seeds \
        --k-rule volume --speed-fraction off --max-time 1.5 --out $W/res/conv6_$tag.json > $W/log/conv6_$tag.log 2>&1
    done ) &
}
# MODE=conv7: Newton at 1e4 one step finer (NEWTON_DTS, default 6.25e-5 s), then polydem at k x 64 near its dt_rec
# (1e4 cubes, seeds 0 and 1)
conv7() {
  ( gpu 0 python benchmarks/peers/pour_scene.py export --grains 10000 --device cuda:0 --out /tmp/pours/pour_10000.json \
      > $W/log/export_10000.log 2>&1
    gpu 0 python -u benchmarks/peers/newton_pour.py --grains 10000 --device cuda:0 --scene /tmp/pours/pour_10000.json \
      --dt-sweep ${NEWTON_DTS:-6.25e-5} --max-time 4 --out $W/res/newton_10000.json > $W/log/newton_10000.log 2>&1
    for seed in 0 1; do
      gpu 0 python -u benchmarks/converged_pile.py --device cuda:0 --sizes 1e4 --settings ${CONV7_SETTINGS:-64x4} \
        --seeds $seed --k-rule volume --speed-fraction off --max-time 1.5 --out $W/res/conv7_s$seed.json \
        > $W/log/conv7_s$seed.log 2>&1
    done ) &
}
# MODE=conv8: the CUDA tests of the toe's kernels (CONV8_TESTS, at most 150 s), then the pour under the power law
# m = 2 (a face contact is a linear spring: its step falls as k^-1/2, no toe), 1e4 cubes: CONV8_JOBS lines of
# "SETTINGS SEEDS TAG"
conv8() {
  ( CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(( $(left) < 150 ? $(left) : 150 )) python -m pytest -q \
      -rf --tb=short -p no:cacheprovider ${CONV8_TESTS:-tests/test_geometry.py tests/test_at_rest.py tests/test_laws.py} \
      > $W/log/pytest.log 2>&1
    while read -r settings seeds tag; do
      [ -z "$settings" ] && continue
      gpu 0 python -u benchmarks/converged_pile.py --device cuda:0 --sizes 1e4 --settings $settings --seeds $seeds \
        --law power --exponent 2 --k-rule volume --speed-fraction off --max-time 1.5 --out $W/res/conv8_$tag.json \
        > $W/log/conv8_$tag.log 2>&1
    done <<< "${CONV8_JOBS:-1x1,16x1,256x1,1024x2 0 a}" ) &
}
# MODE=newton1e6: Newton at 1e6 cubes (the replicated builder), the pour exported as poses only, at NEWTON_DTS
# (default 1e-3 s), --max-time NEWTON_MAX_TIME (default 1.5 s simulated)
newton1e6() {
  ( gpu 0 python benchmarks/peers/pour_scene.py export --grains 1000000 --no-world-vertices \
      --out /tmp/pours/pour_1000000.json > $W/log/export_1e6.log 2>&1
    gpu 0 python -u benchmarks/peers/newton_pour.py --grains 1000000 --device cuda:0 \
      --scene /tmp/pours/pour_1000000.json --dt-sweep ${NEWTON_DTS:-1e-3} --max-time ${NEWTON_MAX_TIME:-1.5} \
      --progress 20 --out $W/res/newton_1e6.json > $W/log/newton_1e6.log 2>&1 ) &
}
# MODE=newtonsize: Newton's pour at NEWTON_N cubes (default 4e5, below the size where its SAP scan wraps, about
# 5.9e5 in this pour: newton_pour.py --sap-estimate) to settled at NEWTON_DTS, --max-time NEWTON_MAX_TIME (default 3)
newtonsize() {
  local n=${NEWTON_N:-400000}
  ( gpu 0 python benchmarks/peers/pour_scene.py export --grains $n --no-world-vertices \
      --out /tmp/pours/pour_$n.json > $W/log/export_$n.log 2>&1
    gpu 0 python -u benchmarks/peers/newton_pour.py --grains $n --device cuda:0 \
      --scene /tmp/pours/pour_$n.json --dt-sweep ${NEWTON_DTS:-1e-3} --max-time ${NEWTON_MAX_TIME:-3} --progress 20 \
      --out $W/res/newton_$n.json > $W/log/newton_$n.log 2>&1 ) &
}
# MODE=small: Newton's pour and polydem's time to settle at NEWTON_N (default 1000), in turn, to section 7's criterion
small() {
  local n=${NEWTON_N:-1000}
  ( NEWTON_N=$n newtonsize; wait
    gpu 0 python -u benchmarks/time_to_settle.py --device cuda:0 --sizes $n --dt-scales 4 --k-rule volume \
      --speed-fraction off --out $W/res/tts_kinetic_${n}_cube_default.json >> $W/log/tts.log 2>&1 ) &
}
# MODE=newtonsap: Newton's own SAP work at 1e6 cubes (a few steps: newton_pour.py records it from its arrays), then
# polydem's time to settle at POLYDEM_SIZES (default 4e5) to section 7's criterion, as the headline row's
newtonsap() {
  ( gpu 0 python benchmarks/peers/pour_scene.py export --grains 1000000 --no-world-vertices \
      --out /tmp/pours/pour_1000000.json > $W/log/export_1e6.log 2>&1
    gpu 0 python -u benchmarks/peers/newton_pour.py --grains 1000000 --device cuda:0 \
      --scene /tmp/pours/pour_1000000.json --dt-sweep 1e-3 --max-time 0.064 \
      --out $W/res/newton_sap_1e6.json > $W/log/newton_sap_1e6.log 2>&1
    for n in ${POLYDEM_SIZES:-4e5}; do
      gpu 0 python -u benchmarks/time_to_settle.py --device cuda:0 --sizes $n --dt-scales 4 --k-rule volume \
        --speed-fraction off --out $W/res/tts_kinetic_${n}_cube_default.json >> $W/log/tts.log 2>&1
    done ) &
}
# MODE=toe1: long steps with the toe of the recommended step (benchmarks/toe_swap.py; 1e4 cubes): TOE_JOBS is a list
# of "K S T SEED" (k factor, step and toe step as multiples of that k's dt_rec)
toe1() {
  ( while read -r k s t seed; do
      [ -z "$k" ] && continue
      gpu 0 python -u benchmarks/toe_swap.py --device cuda:0 --bodies 10000 --k-factor $k --dt-scale $s --toe-step $t \
        --seed $seed --out $W/res/toe_${k}x${s}_t${t}_s$seed.json > $W/log/toe_${k}x${s}_t${t}_s$seed.log 2>&1
    done <<< "${TOE_JOBS:-1 4 1 0
1 4 1 1
16 4 1 0
16 8 1 0
64 16 1 0}" ) &
}
# MODE=split: the step split for the ghost exchange's overlap (issue 27): its CUDA tests (one process; then two MPI
# ranks on GPU 0 against the undivided run, with the MPICH wheel staged in .gpu3), what the split costs and how early
# its first part ends at SPLIT_SIZES (default 1e6 and 1e5 cubes, benchmarks/split_step.py), then polydem's time to
# settle at TTS_SIZES (default 1e3 and 1e4, one after the other in this call), then the CUDA test of the hertz
# resting volume
split() {
  ( CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
      -p no:cacheprovider tests/test_split_step.py > $W/log/pytest_split.log 2>&1
    if [ ! -x /tmp/gpu/prefix/bin/mpiexec ]; then
      python3 -m pip install -q --no-index --no-deps --ignore-installed --prefix /tmp/gpu/prefix /tmp/gpu/mpich-*.whl
    fi
    PATH=/tmp/gpu/prefix/bin:$PATH LD_LIBRARY_PATH=/tmp/gpu/prefix/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH} \
      CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
      -p no:cacheprovider tests/test_distributed.py -k "decomposed and (box_pour-3000-0.004-2-50 or chain-1500-0.05-2)" \
      > $W/log/pytest_mpi.log 2>&1
    for n in ${SPLIT_SIZES:-1000000 100000}; do
      gpu 0 python -u benchmarks/split_step.py --device cuda:0 --bodies $n --out $W/res/split_step_$n.json \
        > $W/log/split_step_$n.log 2>&1
    done
    for n in ${TTS_SIZES:-1e3 1e4}; do
      gpu 0 python -u benchmarks/time_to_settle.py --device cuda:0 --sizes $n --dt-scales 4 --k-rule volume \
        --speed-fraction off --out $W/res/tts_kinetic_${n}_cube_default.json >> $W/log/tts.log 2>&1
    done
    CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
      -p no:cacheprovider tests/test_at_rest.py -k hertz_laws_volume > $W/log/pytest_at_rest.log 2>&1 ) &
}
# MODE=split2: the split step's first part from the pair threads' order (its pairs first, its launch as many threads
# as they need) against the masked split of MODE=split (OLD_PKG3: that commit's package and its split_step.py, built
# by `git archive cc08e7d src/polydem kernels benchmarks/split_step.py benchmarks/settle.py`), at SPLIT_SIZES,
# alternating; then the CUDA tests: the split step, the at-rest volume and rocking tests, two MPI ranks on GPU 0
split2() {
  local old=${OLD_PKG3:-.oldpkg3}
  ( for n in ${SPLIT_SIZES:-1000000 100000}; do
      PYTHONPATH=$old:${PYTHONPATH:-} gpu 0 python -u $old/bench/split_step.py --device cuda:0 --bodies $n \
        --out $W/res/split_masked_$n.json > $W/log/split_masked_$n.log 2>&1
      gpu 0 python -u benchmarks/split_step.py --device cuda:0 --bodies $n --out $W/res/split_ordered_$n.json \
        > $W/log/split_ordered_$n.log 2>&1
    done
    CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
      -p no:cacheprovider tests/test_split_step.py tests/test_at_rest.py -k "split or hertz_laws_volume or rocks" \
      > $W/log/pytest_split.log 2>&1
    if [ ! -x /tmp/gpu/prefix/bin/mpiexec ]; then
      python3 -m pip install -q --no-index --no-deps --ignore-installed --prefix /tmp/gpu/prefix /tmp/gpu/mpich-*.whl
    fi
    PATH=/tmp/gpu/prefix/bin:$PATH LD_LIBRARY_PATH=/tmp/gpu/prefix/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH} \
      CUDA_VISIBLE_DEVICES=0 POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short \
      -p no:cacheprovider tests/test_distributed.py -k "decomposed and (box_pour-3000-0.004-2-50 or chain-1500-0.05-2)" \
      > $W/log/pytest_mpi.log 2>&1 ) &
}
# MODE=nccl: the ghost rows with NCCL on every GPU of the machine (BENCHMARKS.md 28a; nccl4py and the MPICH wheel staged
# in .gpu3): the NCCL CUDA tests (a rank a GPU), then weak scaling at NCCL_SIZES cubes a GPU (default 1e7) and strong
# scaling at NCCL_STRONG cubes (default 1e7), the four exchange modes alternating, with the one-rank references
nccl() {
  [ "$NGPU" -ge 2 ] || { echo "MODE=nccl needs 2 GPUs or more" >&2; exit 2; }
  if [ ! -x /tmp/gpu/prefix/bin/mpiexec ]; then
    python3 -m pip install -q --no-index --no-deps --ignore-installed --prefix /tmp/gpu/prefix /tmp/gpu/mpich-*.whl
  fi
  export PATH=/tmp/gpu/prefix/bin:$PATH LD_LIBRARY_PATH=/tmp/gpu/prefix/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
  export NCCL_NVLS_ENABLE=0
  ( POLYDEM_TEST_DEVICES=cuda:0 timeout $(left) python -m pytest -q -rf --tb=short -p no:cacheprovider \
      tests/test_distributed.py -k nccl_exchange_is > $W/log/pytest_nccl.log 2>&1
    for n in ${NCCL_SIZES:-10000000}; do
      timeout $(left) python -u benchmarks/scaling.py --device cuda --bodies-per-rank $n --warmup 50 --steps 100 \
        --out $W/res/scaling_weak${n}_r1.json > $W/log/scaling_weak${n}_r1.log 2>&1
      timeout $(left) mpiexec -n $NGPU python -u benchmarks/scaling.py --device cuda --bodies-per-rank $n --warmup 50 \
        --steps 100 --overlap both --exchange both --out $W/res/scaling_weak${n}_r$NGPU.json \
        > $W/log/scaling_weak${n}_r$NGPU.log 2>&1
    done
    n=${NCCL_STRONG:-10000000}
    timeout $(left) python -u benchmarks/scaling.py --device cuda --bodies $n --aspect $NGPU --warmup 50 --steps 100 \
      --out $W/res/scaling_strong${n}_r1.json > $W/log/scaling_strong${n}_r1.log 2>&1
    timeout $(left) mpiexec -n $NGPU python -u benchmarks/scaling.py --device cuda --bodies $n --aspect $NGPU \
      --warmup 50 --steps 100 --overlap both --exchange both --out $W/res/scaling_strong${n}_r$NGPU.json \
      > $W/log/scaling_strong${n}_r$NGPU.log 2>&1 ) &
}
if [ "${MODE:-}" = grouping ] || [ "${MODE:-}" = grouping2 ]; then
  [ "$NGPU" -ge 2 ] || { echo "MODE=$MODE needs 2 GPUs (MODE=grouping1 runs on one)" >&2; exit 2; }
fi
if [ "${MODE:-}" = conv1 ]; then
  conv1
elif [ "${MODE:-}" = conv4 ]; then
  conv4
elif [ "${MODE:-}" = conv5 ]; then
  conv5
elif [ "${MODE:-}" = conv6 ]; then
  conv6
elif [ "${MODE:-}" = conv7 ]; then
  conv7
elif [ "${MODE:-}" = conv8 ]; then
  conv8
elif [ "${MODE:-}" = newton1e6 ]; then
  newton1e6
elif [ "${MODE:-}" = newtonsize ]; then
  newtonsize
elif [ "${MODE:-}" = small ]; then
  small
elif [ "${MODE:-}" = newtonsap ]; then
  newtonsap
elif [ "${MODE:-}" = toe1 ]; then
  toe1
elif [ "${MODE:-}" = nccl ]; then
  nccl
elif [ "${MODE:-}" = split ]; then
  split
elif [ "${MODE:-}" = split2 ]; then
  split2
elif [ "${MODE:-}" = mesh ]; then
  mesh
elif [ "${MODE:-}" = mesh2 ]; then
  mesh2
elif [ "${MODE:-}" = mesh3 ]; then
  mesh3
elif [ "${MODE:-}" = mesh4 ]; then
  mesh4
elif [ "${MODE:-}" = mesh5 ]; then
  mesh5
elif [ "${MODE:-}" = tts ]; then
  tts
elif [ "${MODE:-}" = tts2 ]; then
  tts2
elif [ "${MODE:-}" = tts3 ]; then
  tts3
elif [ "${MODE:-}" = grouping1 ]; then
  grouping1
elif [ "${MODE:-}" = grouping2 ]; then
  grouping2
elif [ "${MODE:-}" = grouping ]; then
  grouping
elif [ -n "${RUN_TAPS:-}" ]; then
  tapjob 0 tap_cube_s1 --grains 5000 --width 24 --seed 1 &
  tapjob 0 tap_cube_s2 --grains 5000 --width 24 --seed 2 &
  tapjob 0 tap_tetra_s1 --shape tetrahedron --grains 8000 --width 14 --seed 1 &
elif [ "$NGPU" -ge 4 ]; then
  small_builds 0 &
  gpu 1 python benchmarks/build_time.py --device cuda:0 --sizes 7e7 --steps 20 --no-git --overlap-check device \
    --out $W/res/build_time_settle_7e7_device.json > $W/log/build_7e7.log 2>&1 &
  cuda_tests 2 &
  big_build &
elif [ "$NGPU" -ge 2 ]; then
  ( cuda_tests 0; small_builds 0 ) &
  big_build &
else
  ( cuda_tests 0; small_builds 0 ) &
fi
while [ $SECONDS -lt $END ] && [ -n "$(jobs -r)" ]; do sleep 2; done
# Every process of this session but this shell (timeout puts each job in its own group, not session).
left_over=$(pgrep -s $$ | grep -vx $$); [ -n "$left_over" ] && kill -TERM $left_over 2>/dev/null; sleep 2
left_over=$(pgrep -s $$ | grep -vx $$); [ -n "$left_over" ] && kill -9 $left_over 2>/dev/null; sleep 1
nvidia-smi --query-gpu=name --format=csv > $W/log/gpus.txt 2>&1
tar czf ${OUT:-.}/round.tgz -C $W .
cd $W/log && for f in *.log; do echo "== $f"; grep -v "^Module\|^Warp\|^   \|^$" $f | tail -4 | cut -c1-220; done

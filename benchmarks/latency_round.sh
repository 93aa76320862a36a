#!/bin/bash
# One GPU, one call: what a small pile's step waits on (BENCHMARKS.md 30: at 1e3 cubes Newton is 1.10x ahead and
# polydem's step is one pair's latency). From the repository root, polydem importable; ncu on the PATH or in
# /usr/local/cuda/bin. Every job's timeout is cut to what is left of BUDGET seconds (default 540); the results
# (/tmp/latency_round) are packed into $OUT/latency_round.tgz (or ./...).
#   1. pair_stalls.py: ncu's warp-state sampling of the overlap kernel (one cube or rock pair alone, 1024 one to a
#      warp, and 65,536 packed: the throughput the pair kernel's 2x row asks of it) and of the 1e3 cube pour's own
#      pair and gather kernels 6,000 steps in: the stall reasons and the Python lines they fall on.
#   2. host_share.py at 1e3 and 1e4 cubes: Simulation.step's chunks (their checks and copies) against the bare
#      graph launches of advance(), alternating: the GPU's idle share of a small pile's step.
#   3. time_to_settle.py at 1e3 cubes with --profile-steps 500: the step's wall time against its graph's GPU time
#      and each kernel's GPU time with graphs off, then the same with --no-shared-poly (the per-thread buffer).
set -u
R=/tmp/latency_round; rm -rf $R; mkdir -p $R; END=$((SECONDS + ${BUDGET:-540}))
# never 0 or less: `timeout 0` means no limit at all
cap() { local l=$((END - SECONDS)); [ $l -lt 5 ] && l=5; [ $l -gt $1 ] && l=$1; echo $l; }
export PATH=$PATH:/usr/local/cuda/bin
timeout $(cap 300) python3 benchmarks/pair_stalls.py --device cuda:0 --shapes cube,rock20 \
  --cases one,spread1024,packed65536,pile1000 --out $R/stalls > $R/stalls.log 2>&1
grep -E "^==|^   " $R/stalls.log | head -90
# the reports are large: keep the CSV pages and the summary
mkdir -p $R/reports && mv $R/stalls/*.ncu-rep $R/reports/ 2>/dev/null
timeout $(cap 70) python3 benchmarks/host_share.py --device cuda:0 --sizes 1000,10000 --out $R/host_share.json \
  > $R/host_share.log 2>&1; tail -4 $R/host_share.log
for flag in "" --no-shared-poly; do
  log=$R/tts_1e3${flag:+_thread}
  timeout $(cap 80) python3 benchmarks/time_to_settle.py --device cuda:0 --sizes 1000 --dt-scales 4 --k-rule volume \
    --speed-fraction off --profile-steps 500 $flag --out $log.json > $log.log 2>&1
  echo "tts 1e3 ${flag:-default}: $(grep -E '^ +1000 ' $log.log | tail -1)"
  python3 benchmarks/profile_summary.py "$log.json"
done
mkdir -p ${OUT:-.}
tar czf ${OUT:-.}/latency_round.tgz -C $R --exclude reports . ; tar czf ${OUT:-.}/latency_reports.tgz -C $R reports
ls -la ${OUT:-.}/latency_*.tgz

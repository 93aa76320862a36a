#!/bin/bash
# One GPU (BENCHMARKS.md 28c): the pair kernel's spread pairs (the default) against none (--spread-pairs 0), alternating
# runs in one call: its CUDA tests, time to settled at 1e3 cubes, the step of the mixed and cube piles at 1e3 and 1e4.
# From the repository root, polydem importable; writes $OUT/spread.tgz (or ./spread.tgz). SHAPES (default "mixed
# cube"), SIZES (default "10000 1000") and TTS (default 1: time to settled at 1e3 cubes too) choose the runs; ALT
# (default 0: none) the --spread-pairs the default is run against; TESTS=0 leaves the CUDA tests out.
set -u
R=/tmp/spread; rm -rf $R; mkdir -p $R
ALT=${ALT:-0}
if [ "${TESTS:-1}" = 1 ]; then
  POLYDEM_TEST_DEVICES=cuda:0 timeout 240 python3 -m pytest -q -rf -p no:cacheprovider tests/test_pair_order.py \
    -k "spread or contact_give or ordered_by_cost_give" > $R/pytest_spread.log 2>&1; tail -3 $R/pytest_spread.log
fi
for sp in $( [ "${TTS:-1}" = 1 ] && echo default $ALT default $ALT ); do
  timeout 90 python3 benchmarks/time_to_settle.py --device cuda:0 --sizes 1000 --dt-scales 4 --k-rule volume \
    --speed-fraction off --spread-pairs $sp --out $R/tts_1e3_spread_${sp}_$RANDOM.json > $R/tts_$sp.log 2>&1
  echo "tts 1e3 spread=$sp: $(grep -E '^ +1000 ' $R/tts_$sp.log | tail -1)"
done
for shapes in ${SHAPES:-mixed cube}; do
  for n in ${SIZES:-10000 1000}; do
    for sp in default $ALT default $ALT; do
      timeout 120 python3 benchmarks/settle.py --device cuda:0 --sizes $n --shapes $shapes --precision mixed \
        --no-graph-compare --k-rule volume --warmup-time 0.3 --steps 200 --spread-pairs $sp \
        --out $R/settle_${shapes}_${n}_spread_${sp}_$RANDOM.json > $R/settle.log 2>&1
      echo "settle $shapes $n spread=$sp: $(grep -E "^ +$n " $R/settle.log | tail -1)"
    done
  done
done
tar czf ${OUT:-.}/spread.tgz -C $R .

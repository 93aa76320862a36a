#!/bin/bash
# One GPU: a pair-kernel variant against the default, in one call (BENCHMARKS.md 29, 30). From the repository root,
# polydem importable.
#   VARIANT=shared  the polygon buffer in the block's shared memory (the default since section 31) against the
#                   per-thread buffer (--no-shared-poly, files marked _thread): its CUDA tests, the overlap
#                   kernel's throughput both ways (pair_kernel.py --clips polygon,shared; PAIR=0 leaves it out), time
#                   to settled at 1e3 cubes (TTS=0 leaves it out) and the step of the SHAPES piles (default "mixed
#                   cube") at SIZES (default "10000 100000") with and without, alternating.
#   (VARIANT=lanes, a spread pair's lanes each clipping some of its faces, went with that variant: git tag
#   pair-lanes-30, BENCHMARKS.md sections 30 and 31.) For two trees rather than two flags: ab_round.sh.
# WARMUP: the piles' simulated warm-up in seconds (default 0.3; at 1e6 it takes more than a minute).
# Every job's timeout is cut to what is left of BUDGET seconds (default 540); then the results (/tmp/variant_$VARIANT)
# are packed into $OUT/variant_$VARIANT.tgz (or ./...): one file, as the device returns a limited count.
set -u
VARIANT=${VARIANT:-shared}
R=/tmp/variant_$VARIANT; rm -rf $R; mkdir -p $R; END=$((SECONDS + ${BUDGET:-540}))
# never 0 or less: `timeout 0` means no limit at all
cap() { local l=$((END - SECONDS)); [ $l -lt 5 ] && l=5; [ $l -gt $1 ] && l=$1; echo $l; }
if [ "$VARIANT" != shared ]; then
  echo "variant_round: VARIANT must be shared (the lanes variant is at git tag pair-lanes-30)"; exit 2
fi
FLAG=--no-shared-poly; LABEL=thread; TESTS="tests/test_pair_variants.py -k shared"; SIZES=${SIZES:-10000 100000}
POLYDEM_TEST_DEVICES=cuda:0 timeout $(cap 240) python3 -m pytest -q -rf -p no:cacheprovider ${TESTS%% -k *} \
  -k "${TESTS#* -k }" > $R/pytest.log 2>&1; tail -3 $R/pytest.log
if [ "$VARIANT" = shared ] && [ "${PAIR:-1}" = 1 ]; then
  timeout $(cap 200) python3 benchmarks/pair_kernel.py --device cuda:0 --precisions float32 --shapes cube,rock20,hull64 \
    --depths 0.01,flat --clips polygon,shared,polygon,shared --sample 16 --out $R/pair_kernel_shared.json \
    > $R/pair_kernel.log 2>&1; grep -E "^(cube|rock|hull)" $R/pair_kernel.log
fi
if [ "${TTS:-1}" = 1 ]; then
  for flag in "" $FLAG "" $FLAG; do
    log=$R/tts_1e3${flag:+_$LABEL}_$RANDOM
    timeout $(cap 90) python3 benchmarks/time_to_settle.py --device cuda:0 --sizes 1000 --dt-scales 4 --k-rule volume \
      --speed-fraction off $flag --out $log.json > $log.log 2>&1
    echo "tts 1e3 ${flag:-default}: $(grep -E '^ +1000 ' $log.log | tail -1)"
  done
fi
for shapes in ${SHAPES:-mixed cube}; do
  for n in $SIZES; do
    for flag in "" $FLAG "" $FLAG; do
      log=$R/settle_${shapes}_${n}${flag:+_$LABEL}_$RANDOM
      timeout $(cap 150) python3 benchmarks/settle.py --device cuda:0 --sizes $n --shapes $shapes --precision mixed \
        --no-graph-compare --k-rule volume --warmup-time ${WARMUP:-0.3} --steps 200 $flag --out $log.json \
        > $log.log 2>&1
      echo "settle $shapes $n ${flag:-default}: $(grep -E "^ +$n " $log.log | tail -1)"
    done
  done
done
tar czf ${OUT:-.}/variant_$VARIANT.tgz -C $R .

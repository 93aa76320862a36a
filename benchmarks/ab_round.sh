#!/bin/bash
# One GPU, one call: this tree against another (BEFORE: a .tgz of that tree's root, e.g. `git archive REV -o x.tgz`),
# alternating, on the same machine: the before/after of a kernel change that keeps the bits (BENCHMARKS.md 31).
# From the repository root, polydem importable (this tree, an editable install). The other tree is installed into
# /tmp/ab_before/site and put first on PYTHONPATH for its runs; the benchmark scripts are this tree's for both.
#   JOBS: which measurements, in order (default "tts1e3 settle"):
#     tts1e3   time_to_settle.py at 1e3 cubes with --profile-steps 500 (the step's graph time and each kernel's),
#              before, after, before, after
#     settle   settle.py at SIZES (default "10000 100000") of SHAPES (default "cube mixed"), 200 steps after a
#              WARMUP (default 0.3) s pour, before, after, before, after
#     tests    POLYDEM_TEST_DEVICES=cuda:0 pytest TESTS ("FILES -k EXPRESSION"; default: the gather's, the damping
#              loads' and the shared polygon buffer's tests and the pile's bit-for-bit runs), this tree
# Every job's timeout is cut to what is left of BUDGET seconds (default 540); the results (/tmp/ab_round) are packed
# into $OUT/ab_round.tgz (or ./...): one file, as the device returns a limited count.
set -u
: "${BEFORE:?BEFORE=path to a .tgz of the tree to compare with}"
R=/tmp/ab_round; rm -rf $R; mkdir -p $R; END=$((SECONDS + ${BUDGET:-540}))
cap() { local l=$((END - SECONDS)); [ $l -lt 5 ] && l=5; [ $l -gt $1 ] && l=$1; echo $l; }
B=/tmp/ab_before; rm -rf $B; mkdir -p $B/tree $B/site
tar xzf "$BEFORE" -C $B/tree || { echo "ab_round: cannot unpack $BEFORE"; exit 1; }
python3 -m pip install -q --no-deps --no-build-isolation --no-index --no-compile --target $B/site $B/tree \
  > $R/install_before.log 2>&1 || { echo "ab_round: installing the other tree failed:"; tail -5 $R/install_before.log; }
# which polydem each side imports: the other tree's from its site folder, this one's from the editable install
for side in before after; do
  pp=$([ $side = before ] && echo "$B/site:${PYTHONPATH:-}" || echo "${PYTHONPATH:-}")
  PYTHONPATH=$pp python3 -c "import polydem, polydem.kernels.forces as f; print('$side:', polydem.__file__, f.__file__)"
done | tee $R/sides.txt
run_side() {  # side, then the command
  local side=$1; shift
  if [ $side = before ]; then PYTHONPATH=$B/site:${PYTHONPATH:-} "$@"; else "$@"; fi
}
for job in ${JOBS:-tts1e3 settle}; do
  case $job in
  tests)
    T=${TESTS:-tests/test_damping_load.py tests/test_simulation.py tests/test_pair_variants.py -k \
damping or gather or momentum or bit_identical or shared or pour_settles or regrow}
    POLYDEM_TEST_DEVICES=cuda:0 timeout $(cap 240) python3 -m pytest -q -rf -p no:cacheprovider ${T%% -k *} \
      -k "${T#* -k }" > $R/pytest.log 2>&1; tail -3 $R/pytest.log ;;
  tts1e3)
    for side in before after before after; do
      log=$R/tts_1e3_${side}_$RANDOM
      run_side $side timeout $(cap 90) python3 benchmarks/time_to_settle.py --device cuda:0 --sizes 1000 \
        --dt-scales 4 --k-rule volume --speed-fraction off --profile-steps 500 --out $log.json > $log.log 2>&1
      echo "tts 1e3 $side: $(grep -E '^ +1000 ' $log.log | tail -1)"
      python3 benchmarks/profile_summary.py "$log.json" --top 4 --one-line
    done ;;
  settle)
    for shapes in ${SHAPES:-cube mixed}; do
      for n in ${SIZES:-10000 100000}; do
        for side in before after before after; do
          log=$R/settle_${shapes}_${n}_${side}_$RANDOM
          run_side $side timeout $(cap 150) python3 benchmarks/settle.py --device cuda:0 --sizes $n --shapes $shapes \
            --precision mixed --no-graph-compare --k-rule volume --warmup-time ${WARMUP:-0.3} --steps 200 \
            --out $log.json > $log.log 2>&1
          echo "settle $shapes $n $side: $(grep -E "^ +$n " $log.log | tail -1)"
        done
      done
    done ;;
  *) echo "ab_round: unknown job $job (tts1e3, settle, tests)" ;;
  esac
done
mkdir -p ${OUT:-.}
tar czf ${OUT:-.}/ab_round.tgz -C $R .

#!/bin/bash
# One GPU: the pair kernel's polygon buffer in the block's shared memory (make_geometry's shared_poly) against the
# per-thread buffer (the default), in one call: its CUDA tests, the overlap kernel's throughput (pair_kernel.py
# --clips polygon,shared), and the step of the cube and mixed piles with and without --shared-poly, alternating.
# From the repository root, polydem importable; writes $OUT/shared.tgz (or ./shared.tgz). SIZES (default
# "100000 1000000") and SHAPES (default "cube mixed") choose the piles.
set -u
R=/tmp/shared; rm -rf $R; mkdir -p $R
POLYDEM_TEST_DEVICES=cuda:0 timeout 240 python3 -m pytest -q -rf -p no:cacheprovider tests/test_pair_variants.py \
  -k shared > $R/pytest_shared.log 2>&1; tail -3 $R/pytest_shared.log
timeout 200 python3 benchmarks/pair_kernel.py --device cuda:0 --precisions float32 --shapes cube,rock20,hull64 \
  --depths 0.01,flat --clips polygon,shared,polygon,shared --sample 16 --out $R/pair_kernel_shared.json \
  > $R/pair_kernel.log 2>&1; grep -E "^(cube|rock|hull)" $R/pair_kernel.log
for shapes in ${SHAPES:-cube mixed}; do
  for n in ${SIZES:-100000 1000000}; do
    for flag in "" --shared-poly "" --shared-poly; do
      timeout 150 python3 benchmarks/settle.py --device cuda:0 --sizes $n --shapes $shapes --precision mixed \
        --no-graph-compare --k-rule volume --warmup-time 0.3 --steps 200 $flag \
        --out $R/settle_${shapes}_${n}${flag:+_shared}_$RANDOM.json > $R/settle.log 2>&1
      echo "settle $shapes $n ${flag:-local}: $(grep -E "^ +$n " $R/settle.log | tail -1)"
    done
  done
done
tar czf ${OUT:-.}/shared.tgz -C $R .

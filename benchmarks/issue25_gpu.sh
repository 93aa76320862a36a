#!/bin/bash
# Issue 25 (BENCHMARKS 13): the pair kernel and the settle step of two trees in one call on one GPU.
# Each tree is a folder with pkg/polydem (src/polydem with kernels/ as pkg/polydem/kernels), benchmarks/ and
# tests/reference_geometry.py, e.g. made by `git archive <commit> src kernels benchmarks tests`.
#   bash benchmarks/issue25_gpu.sh pair   BEFORE_DIR AFTER_DIR
#   SIZES=100000 bash benchmarks/issue25_gpu.sh settle BEFORE_DIR AFTER_DIR
#   SIZES=1000000 EXTRA="--warmup 300 --steps 100" bash benchmarks/issue25_gpu.sh settle BEFORE_DIR AFTER_DIR
what=$1; shift
out=${OUT:-.}
for n in ${SIZES:-100000}; do
  for tree in "$@"; do
    tag=$(basename "$tree")
    if [ "$what" = pair ]; then
      (cd "$tree" && PYTHONPATH=$PWD/pkg:$PYTHONPATH python benchmarks/pair_kernel.py --device cuda:0 --sample 16 \
         --precisions float32 --shapes cube,rock20,hull64 --depths 0.01 --out "$out/pair_$tag.json")
    else
      (cd "$tree" && PYTHONPATH=$PWD/pkg:$PYTHONPATH python benchmarks/settle.py --device cuda:0 --sizes "$n" \
         --precision mixed --no-graph-compare ${EXTRA} --out "$out/settle_${tag}_$n.json")
    fi
  done
  [ "$what" = pair ] && break
done

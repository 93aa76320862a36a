#!/bin/bash
# Issue 27: the pair kernel's clipping (kernels/geometry.py: in place, packed face lists, the fan's vertex carried),
# before and after, on one GPU in one call.
#   bash benchmarks/issue27_gpu.sh prepare [REV]   # here: build/before/pkg/polydem from REV (default HEAD; git archive;
#                                                  # build/ is ignored)
#   OUT=DIR bash benchmarks/issue27_gpu.sh mixed   # on the GPU: the mixed pile, pair threads in the orders of
#                                                  # ORDERS (settle.py --pair-thread-order slot|cost|contact|default,
#                                                  # default "slot cost slot cost"), SIZES="1e4 1e5" grains; the cube pile in
#                                                  # CUBE_ORDERS (default: "default", Simulation's own);
#                                                  # an empty list runs none
#   OUT=DIR bash benchmarks/issue27_gpu.sh run     # on the GPU, from this tree with polydem on PYTHONPATH,
#                                                  # carrying build/before
# run: pair_kernel.py (float32; cube, rock20, hull64; 1% deep and flat contacts) with REV's package and with this tree's
# (the same script, which records a SHA-256 of the outputs: equal digests, equal bits). The clip layouts that lost
# (ClipLayout, benchmarks/pair_layouts.py) live at the git tag clip-layouts-27 (BENCHMARKS.md section 14).
set -e
cd "$(dirname "$0")/.."
case "$1" in
prepare)
  rm -rf build/before && mkdir -p build/before/pkg
  git archive "${2:-HEAD}" src/polydem kernels | tar -x -C build/before
  mv build/before/src/polydem build/before/pkg/polydem && rm -rf build/before/pkg/polydem/kernels
  mv build/before/kernels build/before/pkg/polydem/kernels && rmdir build/before/src
  ;;
run)
  out=${OUT:-.}
  common=(--device cuda:0 --sample 16 --precisions float32 --shapes cube,rock20,hull64 --depths 0.01,flat)
  before=$PWD/build/before/pkg
  PYTHONPATH=$before:$PYTHONPATH python benchmarks/pair_kernel.py "${common[@]}" --out "$out/pair_before.json"
  python benchmarks/pair_kernel.py "${common[@]}" --out "$out/pair_after.json"
  python - "$out/pair_before.json" "$out/pair_after.json" <<'PY'
import json, sys
before, after = (json.load(open(p))["rows"] for p in sys.argv[1:])
for b, a in zip(before, after, strict=True):
    same = "same bits" if b["outputs_sha256"] == a["outputs_sha256"] else "BITS DIFFER"
    print(f"{a['shape']:<8} {a['depth']!s:>5} {b['pairs_per_second'] / 1e6:8.1f} -> {a['pairs_per_second'] / 1e6:8.1f} "
          f"M pairs/s ({a['pairs_per_second'] / b['pairs_per_second']:.2f}x), {same}")
PY
  ;;
mixed)
  # The mixed-shape pile (cubes, tetrahedra, 20-vertex rocks, 2:1:1 boxes) with the pair kernel's threads in each
  # order of ORDERS (slot, cost, contact: BENCHMARKS.md 17 and 20), alternating, and the cube pile beside them.
  # The volume rule's k (the corner rule's step is 3.8e-8 s for the tetrahedra: no contact within a call) and 0.3 s
  # of pour: the grains have landed (1e3 mixed on the CPU: 3182 contacts, 5.9 a grain).
  out=${OUT:-.}
  for n in ${SIZES:-10000 100000}; do
    for o in ${ORDERS-slot cost slot cost}; do
      python benchmarks/settle.py --device cuda:0 --sizes $n --shapes mixed --precision mixed --no-graph-compare \
        --k-rule volume --warmup-time 0.3 --steps 200 --pair-thread-order $o --out "$out/mixed_${n}_${o}_$RANDOM.json" \
        | tail -1
    done
    for o in ${CUBE_ORDERS-default}; do
      python benchmarks/settle.py --device cuda:0 --sizes $n --precision mixed --no-graph-compare --k-rule volume \
        --warmup-time 0.3 --steps 200 --pair-thread-order $o --out "$out/cubes_${n}_${o}_$RANDOM.json" | tail -1
    done
  done
  ;;
*)
  echo "usage: $0 prepare [REV] | run | mixed" >&2
  exit 2
  ;;
esac

#!/usr/bin/env bash
# The GPU measurements of issue 13 (BENCHMARKS.md section 8), one part per device call:
#   bash benchmarks/issue13_gpu.sh tests|hopper|repose|scenes|compound  OUT_DIR
set -euo pipefail
part=$1
out=${2:-benchmarks/results/issue13}
mkdir -p "$out"
case $part in
tests)
  POLYDEM_TEST_DEVICES=cuda:0 python -m pytest tests/test_meshwall.py tests/test_analysis.py -q -p no:cacheprovider 2>&1 | tail -2
  python benchmarks/wall_contact_cost.py --device cuda:0 --bodies 10000 --steps 100 --kinds meshT,pair \
    --triangle-edge 2 --out "$out/wall_contact_cost_cuda0_10000_fine.json" | grep -v "^Module"
  ;;
hopper)
  # Beverloo's fit against the number of grains (one size per call: each takes minutes).
  for n in 1000 2000 4000; do
    python benchmarks/hopper_discharge.py --device cuda:0 --grains $n --discharge-time 1.5 \
      --out "$out/hopper_discharge_cuda0_$n.json" | grep -v "^Module"
  done
  ;;
repose)
  # Heaps of cubes, tetrahedra and the non-convex elbow (gated fill, then discharge), two seeds of one
  # shape per call, side by side on one GPU (six at once ran each 3x slower: 1,000 grains take 3-8 min).
  #   SHAPE=cube|tetrahedron|elbow GRAINS=1000 bash benchmarks/issue13_gpu.sh repose OUT_DIR
  n=${GRAINS:-1000}
  shape=${SHAPE:-cube}
  for seed in 1 2; do
    timeout 570 python benchmarks/repose.py --device cuda:0 --grains $n --seeds 1 --first-seed $seed --shapes $shape \
      --fill-time 1.5 --max-time 4 --out "$out/repose_cuda0_${n}_${shape}_seed$seed.json" 2>&1 | grep "seed $seed:" &
  done
  wait
  ;;
compound)
  # Compound grains: the tests on cuda:0 and the cost of a compound contact.
  POLYDEM_TEST_DEVICES=cuda:0 python -m pytest tests/test_compound.py tests/test_meshwall.py tests/test_geometry.py \
    -q -p no:cacheprovider 2>&1 | tail -2
  python benchmarks/compound_contact_cost.py --device cuda:0 --bodies 100000 --steps 100 \
    --out "$out/compound_contact_cost_cuda0_100000.json" | grep -v "^Module"
  ;;
scenes)
  # usd-core is not in the GPU bundle: carry its wheel in .gpu4 (pip download usd-core --no-deps
  # --python-version 3.12 --only-binary=:all: --platform manylinux2014_x86_64 -d .gpu4).
  if ls .gpu4/usd_core-*.whl > /dev/null 2>&1; then
    python -m pip install -q --no-deps --no-index --target /tmp/usd .gpu4/usd_core-*.whl
    export PYTHONPATH=/tmp/usd:${PYTHONPATH:-}
  fi
  # The three scenes from the command line, large: 4000 cubes in the hopper, 3000 in the heap, the
  # mixer three times the size with 3000 grains.
  python - <<'PY'
import re, pathlib
s = pathlib.Path("scenes")
h = (s / "hopper.toml").read_text().replace("count = 800", "count = 4000").replace("max = [0.08, 0.08, 0.62]", "max = [0.08, 0.08, 1.4]")
(s / "hopper_large.toml").write_text(h)
h = (s / "heap.toml").read_text().replace("count = 300", "count = 3000").replace("max = [0.08, 0.08, 0.42]", "max = [0.08, 0.08, 1.3]").replace("duration = 4.0", "duration = 8.0")
(s / "heap_large.toml").write_text(h)
m = (s / "mixer.toml").read_text().replace("count = 120", "count = 3000")
m = m.replace('position = [0.0, 0.0, 0.2]', 'position = [0.0, 0.0, 0.6]\nscale = 3.0')
m = m.replace("region = { min = [-0.14, -0.075, 0.06], max = [0.14, 0.075, 0.34] }", "region = { min = [-0.42, -0.225, 0.18], max = [0.42, 0.225, 1.02] }")
m = m.replace("thickness = 0.007", "thickness = 0.02").replace("thickness = 0.02              # [m]\nangular", "thickness = 0.06\nangular")
(s / "mixer_large.toml").write_text(m)
PY
  for sc in hopper_large heap_large mixer_large; do
    python -m polydem run scenes/$sc.toml --device cuda:0 --out "$out/$sc" 2>&1 | grep -v "^ \+[0-9.]*%\|^Module" | tail -12 || true
  done
  ;;
esac

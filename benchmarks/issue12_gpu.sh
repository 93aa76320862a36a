#!/usr/bin/env bash
# The GPU measurements of BENCHMARKS.md section 7 (issue 12, packings fast), one part per device call
# (see ../shared/gpu/README.md for getting Warp, and Newton for the peer parts, there):
#
#   bash benchmarks/issue12_gpu.sh levers OUTDIR    # register caps, ncu, order, tree
#   bash benchmarks/issue12_gpu.sh settle OUTDIR    # time to settled at 1e4 and 1e5, Newton at 1e4
#   bash benchmarks/issue12_gpu.sh large OUTDIR     # Newton at 1e5, polydem at 1e6 (settled and the step)
#
# The "before" time-to-settle figures of section 7 (tts_base_*.json) were taken on the tree of
# 3f2ab56 with `time_to_settle.py --dt-scales 1,2,3,4` (its k_t = k_n friction spring).
# The pair-kernel variants of section 7c (pair_variants.json, s1e5_buffered_*.json, s1e6_before.json)
# live at the git tag pair-variants-7c, whose copy of this script runs them (in a virtual environment
# of its own, so that polydem is imported from the tag's tree):
#   git worktree add /tmp/pair-variants pair-variants-7c && cd /tmp/pair-variants
#   python -m venv .venv && . .venv/bin/activate && pip install -e . && bash benchmarks/issue12_gpu.sh levers OUTDIR
set -u
part=$1
out=$2
mkdir -p "$out"
B=benchmarks
row() { grep -E "^ +[0-9]+ " | sed "s/^/$1: /"; }

if [ "$part" = levers ]; then
    POLYDEM_TEST_DEVICES=cuda:0 python -m pytest tests/test_pair_variants.py tests/test_broadphase.py -q 2>&1 | tail -2
    common="--device cuda:0 --sizes 100000 --steps 100 --warmup-time 0.1 --no-graph-compare --precision mixed"
    for cap in 0 128 96; do
        python $B/settle.py $common --max-registers $cap --out "$out/s1e5_planes_${cap}.json" 2>&1 | row "planes cap $cap"
    done
    for order in grid shuffled morton; do
        python $B/settle.py $common --order $order --out "$out/s1e5_order_${order}.json" 2>&1 | row "order $order"
    done
    python $B/settle.py --device cuda:0 --sizes 100000 --steps 100 --stage-steps 5 --warmup-time 0.3 --no-graph-compare \
        --precision mixed --tree-rebuild never --tree-compare always --out "$out/settle_1e5_tree.json" 2>&1 | grep "tree:"
    for cap in 0 128; do
        python $B/profile_step.py --device cuda:0 --bodies 100000 --warmup-time 0.1 --max-registers $cap \
            --out "$out/profile_planes_${cap}.json" 2>&1 | tail -3
    done
fi

if [ "$part" = settle ]; then
    T="python $B/time_to_settle.py --device cuda:0 --max-time 2"
    $T --sizes 1e4 --dt-scales 1,2,4,6 --out "$out/tts_1e4.json" 2>&1 | grep -v "^Module" | tail -5
    $T --sizes 1e4 --dt-scales 1,4 --shapes mixed --out "$out/tts_1e4_mixed.json" 2>&1 | grep -v "^Module" | tail -3
    $T --sizes 1e5 --dt-scales 1,4 --out "$out/tts_1e5.json" 2>&1 | grep -v "^Module" | tail -3
    python $B/peers/pour_scene.py export --grains 10000 > /dev/null 2>&1
    python $B/peers/newton_pour.py --grains 10000 --device cuda:0 --dt-sweep 1e-3,5e-4,2.5e-4 --max-time 3 2>&1 | tail -5
    cp $B/results/peers/newton_settle_cuda0_10000.json "$out/"
fi

if [ "$part" = large ]; then
    python $B/peers/pour_scene.py export --grains 100000 > /dev/null 2>&1
    python $B/peers/newton_pour.py --grains 100000 --device cuda:0 --dt-sweep 1e-3,5e-4 --max-time 3 2>&1 | tail -4
    cp $B/results/peers/newton_settle_cuda0_100000.json "$out/"
    python $B/time_to_settle.py --device cuda:0 --max-time 1.5 --sizes 1e6 --dt-scales 4 --out "$out/tts_1e6.json" 2>&1 | tail -2
    common="--device cuda:0 --sizes 1000000 --steps 50 --stage-steps 5 --warmup-time 0.05 --no-graph-compare --precision mixed"
    python $B/settle.py $common --out "$out/s1e6_after.json" 2>&1 | row after
fi

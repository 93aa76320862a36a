#!/usr/bin/env bash
# The GPU measurements of issue 12 (packings fast), in the order they were taken on one lent GPU
# (see ../shared/gpu/README.md for getting Warp there). Each part fits one 10-minute device call:
#
#   bash benchmarks/issue12_gpu.sh levers OUTDIR            # pair-kernel variants, register caps, order, tree
#   bash benchmarks/issue12_gpu.sh settle OUTDIR CAP        # time to settled, polydem and Newton (needs newton)
#
# CAP is the pair kernel's register cap chosen from the first part ("none" for no cap).
set -u
part=$1
out=$2
mkdir -p "$out"
py=python
B=benchmarks

if [ "$part" = levers ]; then
    POLYDEM_TEST_DEVICES=cuda:0 $py -m pytest tests/test_pair_variants.py tests/test_broadphase.py -q -x 2>&1 | tail -2
    $py $B/pair_kernel.py --device cuda:0 --shapes cube,rock20,hull64 --precisions float32 --depths 0.01 --sample 8 \
        --variants buffered,planes,planes+masks,planes+masks+stream-in,planes+masks+popc+stream-in,planes+masks+stream-in+stream-out \
        --out "$out/pair_variants.json" 2>&1 | grep -v "^Module" | tail -20
    common="--device cuda:0 --sizes 100000 --steps 100 --warmup-time 0.05 --no-graph-compare --precision mixed"
    for v in buffered planes+masks+stream-in; do
        for cap in none 128 96 64; do
            extra=""
            if [ "$cap" = none ]; then extra="--max-registers 0"; else extra="--max-registers $cap"; fi
            $py $B/settle.py $common --variants $v $extra --out "$out/settle_1e5_${v}_${cap}.json" 2>&1 | grep -E "^ +100000" | sed "s/^/$v cap $cap: /"
        done
    done
    for order in shuffled morton; do
        $py $B/settle.py $common --order $order --out "$out/settle_1e5_order_${order}.json" 2>&1 | grep -E "^ +100000" | sed "s/^/order $order: /"
    done
    $py $B/settle.py --device cuda:0 --sizes 100000 --steps 100 --warmup-time 0.3 --no-graph-compare --precision mixed \
        --tree-rebuild never --tree-compare always --out "$out/settle_1e5_tree.json" 2>&1 | grep -v "^Module" | tail -6
    for cap in none 128; do
        extra=""
        if [ "$cap" = none ]; then extra="--max-registers 0"; else extra="--max-registers $cap"; fi
        $py $B/profile_step.py --device cuda:0 --bodies 100000 --warmup-time 0.1 $extra --out "$out/profile_step_1e5_${cap}.json" 2>&1 | tail -3
    done
fi

if [ "$part" = settle ]; then
    cap=${3:-none}
    extra=""
    if [ "$cap" = none ]; then extra="--max-registers 0"; else extra="--max-registers $cap"; fi
    T="$py $B/time_to_settle.py --device cuda:0 --max-time 2 $extra"
    $T --sizes 1e4 --dt-scales 1,2,4,6 --out "$out/tts_1e4.json" 2>&1 | grep -v "^Module" | tail -5
    $T --sizes 1e4 --dt-scales 2,4 --tangential-ratio 5.5 --out "$out/tts_1e4_kt_old.json" 2>&1 | grep -v "^Module" | tail -3
    $T --sizes 1e4 --dt-scales 1,4 --shapes mixed --out "$out/tts_1e4_mixed.json" 2>&1 | grep -v "^Module" | tail -3
    $py $B/peers/pour_scene.py export --grains 10000 > /dev/null 2>&1
    $py $B/peers/newton_pour.py --grains 10000 --device cuda:0 --dt-sweep 1e-3,5e-4,2.5e-4 --max-time 3 2>&1 | grep -v "^Module" | tail -8
    cp $B/results/peers/newton_settle_cuda0_10000.json "$out/" 2>/dev/null
    $T --sizes 1e5 --dt-scales 1,4 --out "$out/tts_1e5.json" 2>&1 | grep -v "^Module" | tail -3
fi

if [ "$part" = large ]; then
    cap=${3:-none}
    extra=""
    if [ "$cap" = none ]; then extra="--max-registers 0"; else extra="--max-registers $cap"; fi
    $py $B/peers/pour_scene.py export --grains 100000 > /dev/null 2>&1
    $py $B/peers/newton_pour.py --grains 100000 --device cuda:0 --dt-sweep 1e-3,5e-4 --max-time 3 2>&1 | grep -v "^Module" | tail -6
    cp $B/results/peers/newton_settle_cuda0_100000.json "$out/" 2>/dev/null
    $py $B/time_to_settle.py --device cuda:0 --max-time 2 $extra --sizes 1e6 --dt-scales 4 --out "$out/tts_1e6.json" 2>&1 | grep -v "^Module" | tail -3
    common="--device cuda:0 --sizes 1000000 --steps 100 --warmup-time 0.05 --no-graph-compare --precision mixed"
    $py $B/settle.py $common --variants buffered --out "$out/settle_1e6_before.json" 2>&1 | grep -E "^ +1000000"
    $py $B/settle.py $common $extra --out "$out/settle_1e6_after.json" 2>&1 | grep -E "^ +1000000"
fi

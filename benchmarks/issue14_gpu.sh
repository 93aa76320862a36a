#!/usr/bin/env bash
# The GPU measurements of issue 14 (BENCHMARKS.md section 9) on a machine with 2 GPUs, one call:
#   bash benchmarks/issue14_gpu.sh OUT_DIR [weak|strong|tests|all]
# mpi4py and the MPICH wheel are staged in .gpu3 (bash ../shared/gpu/stage.sh --extra mpi4py --extra mpich).
set -uo pipefail
out=${1:-benchmarks/results/issue14}
what=${2:-all}
mkdir -p "$out"
# The MPICH wheel puts mpiexec and libmpi beside its prefix: install it into one of its own (the
# machine's /usr/bin/mpiexec is Open MPI's, which refuses root and is not the library mpi4py loads here).
if [ ! -x /tmp/gpu/prefix/bin/mpiexec ]; then
  python3 -m pip install -q --no-index --no-deps --ignore-installed --prefix /tmp/gpu/prefix /tmp/gpu/mpich-*.whl
fi
export PATH=/tmp/gpu/prefix/bin:$PATH LD_LIBRARY_PATH=/tmp/gpu/prefix/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
nvidia-smi --query-gpu=name --format=csv,noheader
run() { timeout "$1" mpiexec -n "$2" python benchmarks/scaling.py --device cuda "${@:3}" 2>&1 | grep -v "^Module\|^Warp\|CUDA Toolkit\|Devices:\|\"cuda\|Kernel cache\|/root/.cache" ; }
if [ "$what" = tests ] || [ "$what" = all ]; then
  POLYDEM_TEST_DEVICES=cuda:0 timeout 240 python -m pytest tests/test_distributed.py -q -x -k "one_rank or decomposed" -p no:cacheprovider 2>&1 | tail -3
fi
if [ "$what" = weak ] || [ "$what" = all ]; then
  run 150 1 --bodies-per-rank 1000000 --baseline --out "$out/scaling_cuda_weak1000000_r1.json"
  run 150 2 --bodies-per-rank 1000000 --out "$out/scaling_cuda_weak1000000_r2.json"
  run 200 1 --bodies-per-rank 10000000 --warmup 50 --steps 100 --baseline --out "$out/scaling_cuda_weak10000000_r1.json"
  run 200 2 --bodies-per-rank 10000000 --warmup 50 --steps 100 --out "$out/scaling_cuda_weak10000000_r2.json"
fi
if [ "$what" = strong ] || [ "$what" = all ]; then
  # 1 rank with --aspect 2 is the same pile as the 2 ranks'.
  run 200 1 --bodies 10000000 --aspect 2 --warmup 50 --steps 100 --out "$out/scaling_cuda_strong10000000_r1.json"
  run 200 2 --bodies 10000000 --aspect 2 --warmup 50 --steps 100 --out "$out/scaling_cuda_strong10000000_r2.json"
fi

#!/usr/bin/env bash
# One device session: CUDA kernel tests, kernel benchmark, a 20-view Dark training run.
# Usage (on the GPU machine, Warp installed into /tmp/site): bash scripts/gpu_smoke.sh OUTDIR [steps]
set -u
out=${1:?out dir}; steps=${2:-1500}
export PYTHONPATH=/tmp/site:${PYTHONPATH:-} PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
python3 -m pytest -q -x -k cuda tests/test_hashgrid.py tests/test_occupancy.py tests/test_render.py 2>&1 | tail -8 | tee $out/tests.txt
python3 scripts/bench_kernels.py --device cuda --out $out --no-md 2>&1 | grep -v Warp | tee $out/bench.txt
python3 -c "
import time; t=time.time()
from fastneus.synth.render import synthesize
synthesize('/tmp/dark20', shape='toy', views=20, size=(800,800), pattern='crosslaser', illum='dark', seed=0, device='cuda', progress=False)
print('synth 20x800x800 dark on cuda: %.1fs' % (time.time()-t))
" 2>&1 | grep -v Warp
python3 -m fastneus.cli train /tmp/dark20 --device cuda --out $out/run --overwrite steps=$steps mesh_resolution=384 2>&1 | grep -v "Warp" | tail -12

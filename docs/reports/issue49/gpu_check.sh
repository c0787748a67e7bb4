#!/usr/bin/env bash
# Issue 49's GPU check: one device call of at most ~8 minutes (each step capped by `timeout`; whatever finished comes
# back in $OUT). Prepared 2026-11-28 without a GPU (none was lent to that task): it has not run on one yet.
#   here, once:  bash docs/reports/issue49/gpu_wheels.sh       (the cp312 wheels the device lacks, into .whl/)
#   there:       run(command="bash docs/reports/issue49/gpu_check.sh", carry=[".whl"], timeout_s=560)
#   a CPU rehearsal here (the script's logic, tiny sizes; no install):
#                GPU_CHECK_DEVICE=cpu GPU_CHECK_SEEDS="1 2" GPU_CHECK_STEPS=3 OUT=/tmp/gpu_check bash docs/reports/issue49/gpu_check.sh
# Steps, in the order of what matters most:
#   1. the wheels into /tmp/site (adarl itself from this tree), the versions and the GPU;
#   2. equality on the GPU: tests/test_fast_sac.py (the fused update against TorchRL's SACLoss) and tests/test_packed.py
#      (packed seeds against their solo fused updates, eager and compiled), with ADARL_TEST_DEVICE=cuda;
#   3. the update window (adarl bench --pack): N = 1, 8, 64 seeds, (64, 64), eager;
#   4. the same compiled (algorithm.compile: inductor), N = 8, 64;
#   5. the same at (256, 256), eager, N = 1, 8, 64.
# The simulator is not in these windows (each seed's replay is filled before them): collection steps each seed's env on
# the CPU one after another, which bounds a packed whole run on any device (docs/performance.md, "Packed seeds").
set -u
DEVICE=${GPU_CHECK_DEVICE:-cuda}
SEEDS=${GPU_CHECK_SEEDS:-1 8 64}
STEPS=${GPU_CHECK_STEPS:-30}
OUT=${OUT:?OUT: the folder whose files come back}
LOG=$OUT/gpu_check.log
exec > >(tee -a "$LOG") 2>&1
export MUJOCO_GL=egl PYTHONUNBUFFERED=1 RL_WARNINGS=False
step() { echo; echo "=== $(date -u +%T) $*"; }
if [ "$DEVICE" = cuda ]; then
  step "1. install the carried wheels"
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || { echo "install failed"; exit 1; }
  export PYTHONPATH=$PWD:/tmp/site
  nvidia-smi -L; nproc
fi
PY=${GPU_CHECK_PYTHON:-python3}
[ "$DEVICE" = cpu ] && PY=${GPU_CHECK_PYTHON:-.venv/bin/python}
$PY - <<'PY'
import importlib, platform, warnings
warnings.simplefilter("always")
import torch
print("python", platform.python_version(), "| torch", torch.__version__, "| cuda", torch.cuda.is_available(),
      torch.cuda.get_device_name(0) if torch.cuda.is_available() else "-")
for name in ("tensordict", "torchrl", "gymnasium", "mujoco", "pydantic", "greenlet", "adarl"):
    try:
        m = importlib.import_module(name)
        print(name, getattr(m, "__version__", "?"), m.__file__)
    except Exception as err:  # a wheel built against another torch says so here
        print(name, "FAILED:", type(err).__name__, err)
PY
step "2. equality on $DEVICE (fused vs SACLoss; packed vs solo)"
ADARL_TEST_DEVICE=$DEVICE timeout 100 $PY -m pytest -q -p no:cacheprovider --junitxml=$OUT/equality.xml \
  tests/test_fast_sac.py tests/test_packed.py 2>&1 | tail -40
bench() {  # bench NAME CAP_S ARGS...
  local name=$1 cap=$2; shift 2
  timeout $cap $PY -m adarl.cli bench --pack --envs Hopper-v5 --steps $STEPS --skip 5 --repeats 3 --warmup 300 \
    --threads 1 --output $OUT/$name.json "$@" 2>&1 | grep -v -E "LazyTensorStorage|warnings.warn|UserWarning" | tail -25
}
step "3. update window, (64, 64), eager, N = $SEEDS"
bench update_64 130 --widths 64 --seeds $SEEDS --set device=$DEVICE
step "4. update window, (64, 64), compiled, N = the two largest of $SEEDS"
bench update_64_compiled 110 --widths 64 --seeds $(echo $SEEDS | tr ' ' '\n' | tail -2) --set device=$DEVICE algorithm.compile=true
step "5. update window, (256, 256), eager, N = $SEEDS"
bench update_256 90 --widths 256 --seeds $SEEDS --set device=$DEVICE
step "done"
ls -la $OUT

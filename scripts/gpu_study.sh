#!/bin/bash
# One study on a lent GPU machine, cut at a time limit, its run directory packed so that it comes back.
#
#   bash scripts/gpu_study.sh LIMIT_S NAME [WHEELS=.whl] -- <experiments/run_sequence.py options, no --out>
#
# Runs `run_sequence.py ... --out /tmp/gpu_runs/NAME` for at most LIMIT_S seconds, then packs the run directory
# without its checkpoints (raw/, raw/partial/, results, plots; a study cut off by the limit is reported from
# raw/partial/ with `report.py --partial`) into $OUT/NAME.tgz, beside its log $OUT/NAME.log. Several studies
# can share one GPU: start each with `&` and `wait` (XLA_PYTHON_CLIENT_PREALLOCATE=false is set, and the wheels
# are installed once, by whichever gets there first). WHEELS holds what scripts/offline_wheels.sh downloads for a
# machine without registry access whose image has a CUDA jax; pass "-" when the environment already has the
# project's packages.
set -u
LIMIT=$1; NAME=$2; shift 2
WHEELS=.whl
if [ "${1:-}" != "--" ]; then WHEELS=$1; shift; fi
[ "${1:-}" = "--" ] && shift
OUT=${OUT:-/tmp/gpu_study_out}; mkdir -p "$OUT" /tmp/gpu_runs
if [ "$WHEELS" != "-" ]; then
    # one install for all the studies started together (flock), then every one reads it
    ( flock 9
      [ -e /tmp/site/.done ] || { python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
          --upgrade --target /tmp/site "$WHEELS"/*.whl && touch /tmp/site/.done; } ) 9>/tmp/gpu_study.lock
    [ -e /tmp/site/.done ] || { echo "gpu_study: installing $WHEELS failed" | tee "$OUT/$NAME.log"; exit 1; }
    export PYTHONPATH=/tmp/site:$PWD/src
fi
export PYTHONUNBUFFERED=1 JAX_DEFAULT_MATMUL_PRECISION=highest XLA_PYTHON_CLIENT_PREALLOCATE=false
{
    echo "gpu_study: $NAME limit=${LIMIT}s start=$(date -u +%FT%TZ)"
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1
    python3 -c "import jax, brax, flax, optax, orbax.checkpoint as o; print('jax', jax.__version__, jax.devices(),
'brax', brax.__version__, 'flax', flax.__version__, 'optax', optax.__version__)" 2>&1
    start=$(date +%s)
    timeout "$LIMIT" python3 experiments/run_sequence.py "$@" --out "/tmp/gpu_runs/$NAME" 2>&1
    echo "gpu_study: $NAME exit=$? wall_s=$(( $(date +%s) - start )) end=$(date -u +%FT%TZ)"
} > "$OUT/$NAME.log" 2>&1
tar czf "$OUT/$NAME.tgz" --exclude=checkpoints -C /tmp/gpu_runs "$NAME"
tail -n 3 "$OUT/$NAME.log"

#!/bin/bash
# One short GPU session: the chunk program's throughput (benchmarks/bench_program.py) for several cases, each in
# its own process. The processes compile side by side (compilation is CPU work and dominates a short session),
# then each is timed alone, one after another, so that no timing shares the GPU.
#
#   bash scripts/gpu_throughput.sh [LIMIT_S=540] [WHEELS=.whl]
#
# WHEELS holds what scripts/offline_wheels.sh downloads (for a machine without registry access whose image has a
# CUDA jax); pass "-" when the environment already has the project's packages. Lines go to stdout and, when $OUT
# is set, to $OUT/bench.txt (one key=value line per case) beside each case's log.
set -u
T0=$(date +%s); LIMIT=${1:-540}; WHEELS=${2:-.whl}; OUT=${OUT:-/tmp/gpu_throughput}; mkdir -p "$OUT"
elapsed() { echo $(( $(date +%s) - T0 )); }
if [ "$WHEELS" != "-" ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
        "$WHEELS"/*.whl || exit 1
    export PYTHONPATH=/tmp/site:$PWD/src
fi
export PYTHONUNBUFFERED=1 JAX_DEFAULT_MATMUL_PRECISION=highest XLA_PYTHON_CLIENT_PREALLOCATE=false
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader; echo "cpus=$(nproc)"
  python3 -c "import jax, brax, mujoco; print('jax', jax.__version__, jax.devices(), 'brax', brax.__version__,
'mujoco', mujoco.__version__)"; } 2>&1 | tee "$OUT/gpu.txt"

# family method members tasks budget parts: 512 members = 10,240 environments; 6 = the paper's seeds
# (GPU_CASES="fam method members tasks budget parts;..." replaces the list)
CASES=("ant_goal ppo_tl 512 1 4 parts" "ant_goal comps 512 2 3 no" "ant_goal ppo_tl 6 1 4 no"
       "ant_goal comps 6 2 3 no" "cheetah_vel comps 6 2 3 no")
[ -n "${GPU_CASES:-}" ] && IFS=';' read -r -a CASES <<< "$GPU_CASES"
sync_dir=$(mktemp -d); pids=()
for i in "${!CASES[@]}"; do
    read -r fam method members tasks budget parts <<< "${CASES[$i]}"
    extra=(); [ "$parts" = parts ] || extra=(--no-parts)
    python3 benchmarks/bench_program.py --family "$fam" --method "$method" --members "$members" --tasks "$tasks" \
        --budget "$budget" --repeats 2 "${extra[@]}" --signal "$sync_dir/ready$i" --wait-for "$sync_dir/go$i" \
        > "$OUT/case$i.log" 2>&1 &
    pids+=($!)
done
# Compile until every case is ready or until the time left is what the timings need (about 30 s a case).
reserve=$(( 30 * ${#CASES[@]} + 10 ))
while [ "$(elapsed)" -lt $((LIMIT - reserve)) ]; do
    ready=$(ls "$sync_dir" | grep -c ready); [ "$ready" -eq ${#CASES[@]} ] && break; sleep 2
done
echo "compiled: $(ls "$sync_dir" | grep -c ready) of ${#CASES[@]} cases at $(elapsed)s"
for i in "${!CASES[@]}"; do
    if [ ! -e "$sync_dir/ready$i" ]; then
        kill "${pids[$i]}" 2>/dev/null; echo "case $i (${CASES[$i]}): not compiled by $(elapsed)s"; continue
    fi
    touch "$sync_dir/go$i"
    while kill -0 "${pids[$i]}" 2>/dev/null && [ "$(elapsed)" -lt $((LIMIT - 5)) ]; do sleep 0.5; done
    kill "${pids[$i]}" 2>/dev/null
    line=$(grep "^family=" "$OUT/case$i.log" | tail -n 1)
    echo "${line:-case $i (${CASES[$i]}): no result by $(elapsed)s; $(grep -v Warning "$OUT/case$i.log" | tail -n 1)}" \
        | tee -a "$OUT/bench.txt"
done
for p in "${pids[@]}"; do kill "$p" 2>/dev/null; done
echo "done at $(elapsed)s"

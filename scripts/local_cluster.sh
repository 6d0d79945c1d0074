#!/usr/bin/env bash
# One jcomps run as N processes on this machine: JAX's multi-controller runtime over localhost, the way it runs
# over the hosts of a cluster (docs: README "Running on a cluster"). Each process gets one CPU device (or one GPU
# of several, or a share of one GPU) and a share of the cores for MetaWorld's stepping workers; the members
# (seeds x grid points) are spread over all of them, and process 0 writes the run directory and prints.
#
#   scripts/local_cluster.sh 2 -- --family point_goal --seeds 4 --out runs/two      # run_sequence.py's options
#   scripts/local_cluster.sh 2 -- --out runs/two --resume                           # continue after a failure
#   scripts/local_cluster.sh 2 -- experiments/report.py runs/two                    # another script of ours
#
# Environment: PYTHON (default: the repository's .venv/bin/python, else python); JCOMPS_PORT (the coordinator's
# port; default: a free one); NPROC (XLA:CPU's thread pool per process; default: cores + all the processes'
# devices, the pool one process with all of them has, since float rounding depends on it: N processes then give
# exactly the results of one process with all their devices; the launcher says N through JCOMPS_LOCAL_PROCESSES); JCOMPS_METAWORLD_WORKERS (default: cores / N, rounded up). Exit code: the first
# non-zero exit code of a process, else 0. If a process dies, the others stop by themselves (exit code 3, at
# their next exchange, or within --heartbeat-timeout seconds).
set -euo pipefail

usage() {
  echo "usage: $0 N -- [SCRIPT.py] ARGS...   (N >= 1 processes; SCRIPT default experiments/run_sequence.py)" >&2
  exit 2
}

[[ $# -ge 2 && "${1:-}" =~ ^[0-9]+$ && "$1" -ge 1 && "$2" == "--" ]] || usage
N=$1
shift 2
here=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
if [[ -z "${PYTHON:-}" ]]; then
  PYTHON=python
  [[ -x "$here/.venv/bin/python" ]] && PYTHON="$here/.venv/bin/python"  # the README's install
fi

script="$here/experiments/run_sequence.py"
if [[ "${1:-}" == *.py ]]; then
  script=$1
  shift
fi
# One CPU device per process (on a GPU machine the GPUs are used instead), unless --devices is given or a run is
# resumed (it takes the count it was made with).
extra=()
if [[ "$script" == */run_sequence.py ]] && ! printf '%s\n' "$@" | grep -qE -- '^--(devices|resume)(=|$)'; then
  extra=(--devices 1)
fi

port=${JCOMPS_PORT:-$("$PYTHON" -c 'import socket; s = socket.socket(); s.bind(("localhost", 0)); print(s.getsockname()[1])')}
cores=$("$PYTHON" -c 'from jcomps.runner import hostdevices; print(hostdevices.cores())')
# Each process sizes XLA:CPU's thread pool as one process with all N processes' devices would (jcomps.runner.hostdevices).
export JCOMPS_LOCAL_PROCESSES=$N
# MetaWorld's stepping workers: each process its share of the cores (the processes are not pinned to cores: XLA
# spreads a device's program over more than one core, and pinning cost Point Goal's chunk program 9%).
export JCOMPS_METAWORLD_WORKERS=${JCOMPS_METAWORLD_WORKERS:-$(((cores + N - 1) / N))}
gpus=0
if command -v nvidia-smi >/dev/null 2>&1; then
  gpus=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU' || true)
fi

pids=()
trap 'kill "${pids[@]}" 2>/dev/null || true' INT TERM
for ((i = 0; i < N; i++)); do
  (
    if ((gpus >= N)); then  # one GPU per process: the i-th of those visible
      IFS=, read -r -a visible <<< "${CUDA_VISIBLE_DEVICES:-$(seq -s, 0 $((gpus - 1)))}"
      export CUDA_VISIBLE_DEVICES=${visible[$i]}
    elif ((gpus > 0)); then  # processes share the GPUs, allocating as they need (untested: NCCL may refuse)
      export XLA_PYTHON_CLIENT_PREALLOCATE=false
    fi
    exec "$PYTHON" "$script" "$@" ${extra[@]+"${extra[@]}"} --coordinator "localhost:$port" --num-processes "$N" \
      --process-id "$i"
  ) &
  pids+=($!)
done

status=0
for pid in "${pids[@]}"; do
  code=0
  wait "$pid" || code=$?
  if ((status == 0 && code != 0)); then
    status=$code
  fi
done
exit "$status"

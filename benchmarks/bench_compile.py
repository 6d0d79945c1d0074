"""Start-up cost of a run: per compiled program, the time to trace, lower and compile it; end to end, the time
from starting ``run_sequence.py`` to its first training iteration, cold and from the compile cache.

``programs`` mode (the default) builds the runner's programs for each family × method exactly as
``experiments/run_sequence.py`` does with its defaults (``jcomps.runner.programs.Programs``: members sharded over the
devices, the default evaluations) and times apart, for each program (``jcomps.runner.programs.PARTS``: ``init``,
``learn``: one task's learning, the program a run waits for, ``evaluate_task``: the evaluations after each task,
``measure``: the held-out meta-test and learnt tasks after each chunk):

- ``trace_s``: Python tracing to a jaxpr (``jit(f).trace``);
- ``lower_s``: lowering to StableHLO (``.lower()``);
- ``compile_s``: XLA's compile (``.compile()``), with the persistent compile cache off;
- ``hlo_kb``: the size of the lowered module's text; ``ops``: its StableHLO operations.

``start`` mode runs ``run_sequence.py`` (``--run-args``) in a subprocess, twice with one fresh compile cache
directory, and prints the seconds to the first training iteration's progress line (``first_iteration_s``), the
longest wait between two output lines (``longest_silence_s``) and, unless ``--until first``, to the end
(``total_s``) of each: ``cache=cold`` then ``cache=warm`` (a second identical run, as a ``--resume`` would).

One line per case, ``key=value`` pairs. Run it alone: compile times are CPU-bound.

    python benchmarks/bench_compile.py --families cheetah_vel ant_goal --methods comps ppo_tl
    python benchmarks/bench_compile.py --mode start --until first \
        --run-args "--family cheetah_vel --methods comps --num-tasks 2"
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time

from jcomps.runner import hostdevices


def bench_programs(family_name: str, method: str, seeds: int, devices: int, num_tasks: int,
                   programs: list[str]) -> list[str]:
    import jax
    import numpy as np

    from jcomps import continual, envs, methods
    from jcomps.runner import grid as grids
    from jcomps.runner.members import method_keys, padded_seeds, task_eval_keys, task_sequences
    from jcomps.runner.programs import Programs

    family = envs.make(family_name)
    config = methods.resolve_config(method, family, num_tasks=num_tasks)  # as run_sequence.py builds it
    eval_config = continual.EvalConfig().resolve(family_name)
    spec, = grids.programs(method, config, ())
    program = Programs().get(method, family_name, spec.config, eval_config, 2, devices)
    member_seeds = list(range(padded_seeds(seeds, devices)))
    # The run's inputs as the runner binds them (``_ProgramRun``), and each part's arguments from them.
    bound = program.bind(task_sequences(family, "non-stationary", member_seeds, num_tasks),
                         np.arange(len(member_seeds), dtype=np.int32), task_eval_keys(member_seeds), {},
                         jax.device_get(envs.held_out(family)))
    rngs = method_keys(member_seeds)
    states = program.init(rngs)
    args = {"init": (program._init, (rngs, {}))}
    args.update({part: (getattr(program, "_" + part), bound.arguments(part, states))
                 for part in ("learn", "evaluate_task", "measure")})
    lines = []
    for name in programs:
        if name not in args:
            continue
        fn, fn_args = args[name]
        t0 = time.perf_counter()
        traced = fn.trace(*fn_args)
        t1 = time.perf_counter()
        lowered = traced.lower()
        t2 = time.perf_counter()
        compiled = lowered.compile()
        t3 = time.perf_counter()
        text = lowered.as_text()
        del compiled
        ops = len(re.findall(r"^\s*(?:%\S+ = )?\"?stablehlo\.", text, re.M))
        lines.append(f"family={family_name} method={method} program={name} seeds={seeds} devices={devices} "
                     f"trace_s={t1 - t0:.1f} lower_s={t2 - t1:.1f} compile_s={t3 - t2:.1f} "
                     f"total_s={t3 - t0:.1f} hlo_kb={len(text) // 1024} ops={ops}")
        print(lines[-1], flush=True)
    return lines


def bench_start(run_args: str, cache: str, label: str, until_first: bool = False) -> str:
    """Runs run_sequence.py with ``run_args`` and the compile cache ``cache``; seconds to the first training
    iteration line and to the end (``until_first``: stopped there)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = tempfile.mkdtemp(prefix="bench_compile_run_")
    command = [sys.executable, "-u", os.path.join(root, "experiments", "run_sequence.py"), *shlex.split(run_args),
               "--out", os.path.join(out, "run"), "--compile-cache", cache]
    start = time.perf_counter()
    first = None
    longest_silence, last = 0.0, start
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    for line in proc.stdout:
        now = time.perf_counter()
        longest_silence, last = max(longest_silence, now - last), now
        sys.stderr.write(f"  [{now - start:6.1f}s] {line}")
        if first is None and re.search(r"\] task \S+ iteration \d+", line):
            first = now - start
            if until_first:
                proc.kill()
                break
    proc.wait()
    total = time.perf_counter() - start
    if proc.returncode != 0 and not until_first:
        raise SystemExit(f"run_sequence.py exited with {proc.returncode}")
    first_text = "none" if first is None else f"{first:.1f}"
    return (f"mode=start cache={label} first_iteration_s={first_text} total_s={total:.1f} "
            f"longest_silence_s={longest_silence:.1f} args={run_args.replace(' ', '_')}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mode", choices=("programs", "start"), default="programs")
    parser.add_argument("--families", nargs="+", default=["cheetah_vel", "ant_goal"])
    parser.add_argument("--methods", nargs="+", default=["comps", "ppo_tl"])
    parser.add_argument("--programs", nargs="+", default=["init", "learn", "evaluate_task", "measure"])
    parser.add_argument("--until", choices=("first", "end"), default="end",
                        help="start mode: stop each run at its first training iteration, or let it finish")
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--devices", type=int, default=None, help="host devices (default: one per core)")
    parser.add_argument("--num-tasks", type=int, default=2)
    parser.add_argument("--run-args", default="--family cheetah_vel --methods comps --num-tasks 2",
                        help="start mode: run_sequence.py's options")
    args = parser.parse_args()
    if args.mode == "start":
        cache = tempfile.mkdtemp(prefix="bench_compile_cache_")
        for label in ("cold", "warm"):
            print(bench_start(args.run_args, cache, label, args.until == "first"), flush=True)
        return
    devices = args.devices or min(hostdevices.cores(), args.seeds)
    hostdevices.configure(devices)
    import jax

    jax.config.update("jax_enable_compilation_cache", False)
    for family in args.families:
        for method in args.methods:
            bench_programs(family, method, args.seeds, devices, args.num_tasks, args.programs)


if __name__ == "__main__":
    main()

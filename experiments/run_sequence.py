"""Run continual-learning methods over a task sequence: checkpoints, resume, results, plots.

    python experiments/run_sequence.py                 # CoMPS vs PPO+TL, 6 Point Goal tasks, 4 seeds (CPU, minutes)
    python experiments/run_sequence.py --methods comps ppo_tl --sequence stationary --num-tasks 20 --seeds 6
    python experiments/run_sequence.py --family cheetah_vel --num-tasks 40 --seeds 6 --budget 500 --out runs/cheetah
    python experiments/run_sequence.py --out runs/cheetah --resume       # continue after a kill
    python experiments/run_sequence.py --methods ppo_tl --grid learning_rate=0.01,0.005,0.001,0.0001 \
        --grid init_std=0.3,0.5,0.7                                      # 12 grid points x 4 seeds, one program
    python experiments/run_sequence.py --methods comps gmps_ppo_is_x2 gmps_ppo_is gmps_ppo gmps ppo_tl \
        --num-tasks 6 --seeds 2 --out runs/ladder                        # the paper's ablation ladder
    python experiments/run_sequence.py --methods comps gmps_ppo --set gmps_ppo.meta.inner_learning_rate=0.01

Every option is derived from a config dataclass (``RunConfig``, ``EvalConfig`` and the methods' configs);
``--help`` lists them. Seeds are a vmap axis sharded over the JAX devices (on CPU, ``--devices`` host devices
let every core work). The run directory gets ``run.json``, checkpoints after every chunk of tasks,
``results.json``, ``plots/*.png`` and ``significance.md``; ``experiments/report.py DIR`` regenerates the last
three. ``--grid FIELD=V1,V2,...`` (repeatable) runs every method at every point of the product of the values, an
axis like the seeds (see ``jcomps.runner.grid``). ``--set METHOD.FIELD[.FIELD]=VALUE`` changes one method alone.
Bad options exit with code 2 and a message naming the option.
"""

from __future__ import annotations

import os
import sys


def _set_host_devices(argv, processes: int = 1) -> None:
    """``--devices N`` must reach XLA before JAX is imported (the CPU device count and its thread pool; with several
    processes, each process's own). Without it: the count stored in the run directory on ``--resume`` (identical
    results need the same count; the stored count is over all ``processes``), else one device per core."""
    def option(name):
        for i, arg in enumerate(argv):
            if arg == name and i + 1 < len(argv):
                return argv[i + 1]
            if arg.startswith(name + "="):
                return arg.split("=", 1)[1]
        return None

    count = option("--devices")
    if count is None and "--resume" in argv and option("--out") is not None:
        from jcomps.runner.files import stored_devices

        stored = stored_devices(option("--out"))
        ok = stored is not None and stored >= processes and stored % processes == 0
        count = str(stored // processes) if ok else None  # else the resume is refused, naming the counts
    from jcomps.runner import hostdevices

    if count is None:
        hostdevices.configure(hostdevices.cores())
    elif count.isdigit() and int(count) >= 1:
        hostdevices.configure(int(count))


def _start(argv):
    """Before JAX starts: this process's place in a run of several (``jcomps.runner.distributed``), then its host
    devices, then joining the others."""
    from jcomps.runner import distributed

    cluster = distributed.from_argv(argv, "run_sequence.py")
    _set_host_devices(argv, cluster.num_processes)
    distributed.start(cluster)
    return cluster


if __name__ == "__main__":
    _start(sys.argv[1:])

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from jcomps import configs, continual, envs, methods  # noqa: E402
from jcomps.analysis import report  # noqa: E402
from jcomps.runner import checkpoint, compile_cache, description, distributed, experiment, hostdevices, rundir  # noqa: E402
from jcomps.runner.files import RunError  # noqa: E402
from jcomps.runner.programs import Programs  # noqa: E402

from jcomps.console import Console  # noqa: E402

# This process's compiled programs: a resume or a second run in the same process (the tests) does not compile
# again. The library keeps no such cache of its own.
PROGRAMS = Programs()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="run_sequence.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=None, help="run directory (default: runs/<family>-<time>)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out from its last checkpoint (options must match it)")
    parser.add_argument("--devices", type=int, default=None,
                        help="CPU host devices to spread the seeds over (default: one per core). Seeds are rounded "
                             "up to a multiple of the devices used; the extra ones are not reported. On a GPU "
                             "machine the run uses the GPUs instead")
    parser.add_argument("--tensorboard", action="store_true", help="also write TensorBoard logs (tensorboardX)")
    parser.add_argument("--wandb", default=None, metavar="PROJECT",
                        help="also log the TensorBoard scalars to Weights & Biases project PROJECT, one run per "
                             "method, offline unless WANDB_MODE says otherwise (files in OUT/wandb; `wandb sync` "
                             "uploads them); needs pip install -e '.[wandb]'")
    parser.add_argument("--wandb-group", default=None, metavar="NAME",
                        help="the W&B group of the runs (default: the run directory's name)")
    parser.add_argument("--compile-cache", default=os.environ.get(compile_cache.ENV), metavar="DIR",
                        help="JAX's persistent compilation cache: a second identical run, or a --resume, loads its "
                             "programs instead of compiling them; none: off (default: $JCOMPS_COMPILE_CACHE, else "
                             f"{compile_cache.default_directory()})")
    parser.add_argument("--grid", dest="grid_specs", action="append", default=None, metavar="FIELD=VALUES",
                        help="a hyperparameter grid axis, VALUES comma-separated (repeat --grid for more axes; the "
                             "run takes the product of the values × the seeds): any method config field, e.g. "
                             "learning_rate=0.01,0.001 or hidden_sizes=128x64,64x32. Continuous hyperparameters run "
                             "in one compiled program; fields that change shapes run one program per value. On "
                             "--resume the stored grid is used (a different one is refused)")
    parser.add_argument("--baseline", default=None, metavar="METHOD",
                        help="the method the significance table compares every other one with (default: comps when "
                             "it runs); one of --methods")
    parser.add_argument("--set", dest="set_specs", action="append", default=None, metavar="METHOD.FIELD=VALUE",
                        help="change one method's config alone, by the field's full path (repeatable), e.g. --set "
                             "gmps_ppo_is.meta.inner_learning_rate=0.01 or --set comps.ppo.hidden_sizes=64x32; wins "
                             "over the shared options, recorded in run.json (on --resume the stored ones are used; "
                             "different ones are refused)")
    distributed.add_args(parser)
    configs.add_config_args(parser, [description.RunConfig, continual.EvalConfig])
    configs.add_config_args(parser, [methods.config_class(m) for m in methods.METHODS], envs.settings_by_field(),
                            methods.settings_by_field())
    return parser


def parse_args(argv=None) -> argparse.Namespace:
    """The command line, parsed (bad words exit 2 naming the option); ``describe`` resolves it into a run."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.devices is not None and args.devices < 1:
        parser.error(f"--devices must be >= 1, got {args.devices}")
    import jax

    if args.devices is not None and jax.default_backend() == "cpu" and args.devices > hostdevices.cores():
        parser.error(f"--devices {args.devices}: this machine has {hostdevices.cores()} cores; allowed: 1 to "
                     f"{hostdevices.cores()} host devices (one per core; more only slow every seed down)")
    if args.resume and not args.out:
        parser.error("--resume needs --out, the run directory to continue")
    return args


def describe(args: argparse.Namespace) -> description.RunDescription:
    """The run the parsed command line asks for (``jcomps.runner.description.resolve``: on --resume over the stored
    run); a value the library refuses exits 2 naming the option."""
    stored = None
    if args.resume:
        try:
            stored = rundir.read(args.out)
        except RunError as err:  # a missing or unreadable run.json
            build_parser().error(f"--resume: {err}" + ("; start it without --resume" if "holds no run" in str(err)
                                                       else ""))
    try:
        described = description.resolve(configs.shared_options(args), set_specs=args.set_specs,
                                         grid_specs=args.grid_specs, stored=stored)
        report.check_baseline(args.baseline, described.run.methods)
    except ValueError as err:
        build_parser().error(str(err))
    if described.run.tasks and not args.resume and description.heldout_chosen(described):
        print(f"warning: --tasks {' '.join(description.heldout_chosen(described))}: held out by "
              f"{described.run.family} (its meta-test tasks); the held-out results of this run are not of unseen "
              f"tasks", file=sys.stderr, flush=True)
    return described


def description_of(argv) -> description.RunDescription:
    """The run the command line ``argv`` describes (``parse_args``, then ``describe``), e.g. to inspect the configs
    a command would run."""
    return describe(parse_args(argv))


def default_out(family: str) -> str:
    """Where a run without --out goes."""
    return os.path.join("runs", f"{family}-{time.strftime('%Y%m%d-%H%M%S')}")


def main(argv=None):
    args = parse_args(argv)
    run = describe(args)
    args.out = args.out or default_out(run.run.family)
    cluster = distributed.settings(args)
    try:
        cache = compile_cache.configure(args.compile_cache)
    except ValueError as err:
        print(f"run_sequence.py: error: --compile-cache: {err}", file=sys.stderr)
        sys.exit(2)
    writer = distributed.is_writer()
    if writer:
        print(f"compile cache: {cache or 'off'}" + ("" if cache is None or compile_cache.callbacks_cached() else
                                                  " (programs with progress callbacks are not cached by this jax)"),
              flush=True)
    if cluster.distributed:
        _say_processes(cluster, writer)
    try:
        console = (Console(lambda line: print(line, flush=True), args.out, args.tensorboard, wandb=args.wandb,
                           wandb_group=args.wandb_group) if writer else None)
        receiver = distributed.progress_receiver(console)
        experiment.run(args.out, run, resume=args.resume, progress_fn=receiver, programs=PROGRAMS)
        distributed.close_receiver(receiver)
        if console is not None:
            console.close()
        if not writer:  # process 0 writes the report and prints the results
            return
        results = report.write(args.out, baseline=args.baseline)
    except RunError as err:
        print(f"error: {err}", file=sys.stderr)
        if cluster.distributed:
            distributed.exit_now(2)
        sys.exit(2)
    except OSError as err:
        if not checkpoint.disk_full(err):
            raise
        # Raw results, run.json or the report on a full disk (a checkpoint says so itself, as a RunError above).
        print(f"error: no space left on the device writing {err.filename or args.out}; free space there, then "
              f"continue with --out {args.out} --resume (from the run's last checkpoint)", file=sys.stderr)
        if cluster.distributed:
            distributed.exit_now(2)
        sys.exit(2)
    except Exception as err:  # noqa: BLE001 - a process of several stops at once so that the others see it gone
        if not cluster.distributed:
            raise
        distributed.report_and_exit(err, cluster)
    print(f"\nmean iterations-to-success per task ({run.run.seeds} seeds):")
    for name, m in results["methods"].items():
        print(f"  {name:14s} {np.round(m['iterations_to_success_mean'], 1).tolist()}")
    best = results.get("best", {m: m for m in results["methods"]})
    if "best" in results:
        print("best grid point per method: " + ", ".join(best.values()))
    half = run.run.num_tasks // 2
    if half >= 1:
        later = {n: float(np.mean(np.asarray(results["methods"][n]["iterations_to_success"])[:, half:]))
                 for n in best.values()}
        print(f"mean over tasks {half + 1}-{run.run.num_tasks}: " +
              ", ".join(f"{n} {v:.1f}" for n, v in later.items()))
    print(open(os.path.join(args.out, "significance.md")).read())
    print(f"results, plots and checkpoints in {args.out}/")


def _say_processes(cluster, writer: bool) -> None:
    """One line per process: where it is in the run and which members it computes."""
    import jax

    print(f"process {cluster.process_id} of {cluster.num_processes}" +
          (f" ({cluster.detected})" if cluster.detected else "") + f": {jax.local_device_count()} of "
          f"{jax.device_count()} devices; " + ("writes the run directory and shows every process's progress"
                                               if writer else "its progress goes to process 0"), flush=True)


if __name__ == "__main__":
    main()

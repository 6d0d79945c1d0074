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

import json
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
        try:
            with open(os.path.join(option("--out"), "run.json")) as f:
                stored = json.load(f).get("devices")
            ok = isinstance(stored, int) and stored >= processes and stored % processes == 0
            count = str(stored // processes) if ok else None  # else the resume is refused, naming the counts
        except (OSError, ValueError, AttributeError):
            pass  # parse_args reports a missing or unreadable run directory
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
from jcomps.analysis import report
from jcomps.runner import checkpoint, compile_cache, distributed, experiment, hostdevices, rundir  # noqa: E402
from jcomps.runner import grid as grids  # noqa: E402
from jcomps.runner.programs import Programs  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from progress import Console  # noqa: E402

# This process's compiled programs: a resume or a second run in the same process (the tests) does not compile
# again. The library keeps no such cache of its own.
PROGRAMS = Programs()


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
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
    configs.add_config_args(parser, [experiment.RunConfig, continual.EvalConfig])
    configs.add_config_args(parser, [methods.config_class(m) for m in methods.METHODS], envs.settings_by_field())
    args = parser.parse_args(argv)
    if args.devices is not None and args.devices < 1:
        parser.error(f"--devices must be >= 1, got {args.devices}")
    import jax

    if args.devices is not None and jax.default_backend() == "cpu" and args.devices > hostdevices.cores():
        parser.error(f"--devices {args.devices}: this machine has {hostdevices.cores()} cores; allowed: 1 to "
                     f"{hostdevices.cores()} host devices (one per core; more only slow every seed down)")
    if args.resume and not args.out:
        parser.error("--resume needs --out, the run directory to continue")
    try:
        if args.resume:
            _from_stored(args)
        else:
            _from_options(args)
        _grid(args)
    except (ValueError, TypeError) as err:
        parser.error(str(err))
    if args.baseline is not None and args.baseline not in args.run.methods:
        parser.error(f"--baseline {args.baseline}: not one of --methods ({', '.join(args.run.methods)})")
    family = envs.make(args.run.family)
    available = len(args.run.tasks or family.task_values)
    if args.run.num_tasks > available:
        parser.error(f"--num-tasks must be in [1, {available}] for {args.run.family}, got {args.run.num_tasks}")
    if args.run.tasks and not args.resume:
        held = {family.task_name(v) for v in family.held_out_values}
        if any(t in held for t in args.run.tasks):
            print(f"warning: --tasks {' '.join(t for t in args.run.tasks if t in held)}: held out by {family.name} "
                  f"(its meta-test tasks); the held-out results of this run are not of unseen tasks", file=sys.stderr,
                  flush=True)
    for name, config in args.configs.items():
        for point in args.points[name]:
            max_tasks = methods.task_slots(point.config)
            if max_tasks is not None and max_tasks < args.run.num_tasks:
                option = ("--grid max_tasks=" if any(a.field == "max_tasks" for a in args.grid) else "--max-tasks ")
                parser.error(f"{option}{max_tasks} is smaller than --num-tasks {args.run.num_tasks} ({name} keeps "
                             f"one experience slot per task)")
    return args


def _grid(args):
    """``args.grid`` from ``--grid`` (or, on --resume without it, the stored grid), checked: every field known to
    a method of the run, not also given as a plain option, every value accepted by the configs (``args.points``:
    every method's grid points, their configs built)."""
    classes = {name: methods.config_class(name) for name in args.run.methods}
    if args.grid_specs:
        args.grid = grids.parse(args.grid_specs, classes)
    else:
        args.grid = grids.from_json(getattr(args, "stored", {}).get("grid"), classes)
    for axis in args.grid:
        if getattr(args, f"cfg_{axis.field}", None) is not None:
            raise ValueError(f"--grid {axis.field}: also given as --{axis.field.replace('_', '-')}; give its values "
                             f"on the grid only")
        for method, values in args.overrides.items():
            if any(key.split(".")[-1] == axis.field for key in values):
                raise ValueError(f"--grid {axis.field}: also given by --set for {method}; give its values on the "
                                 f"grid only")
    args.points = {name: grids.points(name, args.configs[name], args.grid) for name in args.run.methods}


def _count_chosen_tasks(args):
    """--tasks without --num-tasks: as many tasks as given (on --resume too, so that a different list is refused as
    such by the run directory's check, not by its count)."""
    if args.cfg_tasks and args.cfg_num_tasks is None:
        args.cfg_num_tasks = len(args.cfg_tasks)


def _from_options(args):
    _count_chosen_tasks(args)
    args.run = configs.build_config(experiment.RunConfig, args)
    args.eval = configs.build_config(continual.EvalConfig, args)
    # Each method's config from its layers (methods.resolve_config): its registered default on the family, the
    # shared options, one task slot per task, then --set for that method alone.
    defaults = {name: methods.default_config(name, args.run.family) for name in args.run.methods}
    args.overrides = configs.parse_overrides(args.set_specs, defaults)
    args.configs = {name: methods.resolve_config(name, args.run.family, shared=configs.shared_options(args),
                                                 num_tasks=args.run.num_tasks, overrides=args.overrides.get(name))
                    for name in args.run.methods}
    args.out = args.out or os.path.join("runs", f"{args.run.family}-{time.strftime('%Y%m%d-%H%M%S')}")


def _from_stored(args):
    """On --resume the stored run is the base; options given again must agree with it (checked later)."""
    path = os.path.join(args.out, "run.json")
    if not os.path.isfile(path):
        raise ValueError(f"--resume: {args.out} holds no run (no run.json); start it without --resume")
    stored = rundir.read_json(path)
    args.stored = stored
    _count_chosen_tasks(args)
    args.run = configs.config_from_dict(experiment.RunConfig(), stored["run"], args)
    args.eval = configs.config_from_dict(continual.EvalConfig(), stored["eval"], args)
    # Each method's stored config over its registered default on the family (a field missing from an older run.json
    # keeps the method's default, not its config class's), the options given again, and --set (given again: over
    # the stored configs; open_run_dir refuses any difference).
    defaults = {name: methods.default_config(name, args.run.family) for name in args.run.methods}
    args.overrides = (configs.parse_overrides(args.set_specs, defaults) if args.set_specs
                      else stored.get("overrides", {}))
    args.configs = {name: methods.resolve_config(name, args.run.family, stored=stored["methods"].get(name, {}),
                                                 shared=configs.shared_options(args),
                                                 overrides=args.overrides.get(name))
                    for name in args.run.methods}


def main(argv=None):
    args = parse_args(argv)
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
        experiment.run(args.out, args.run, args.eval, args.configs, resume=args.resume, progress_fn=receiver,
                       grid=args.grid, overrides=args.overrides, programs=PROGRAMS)
        distributed.close_receiver(receiver)
        if console is not None:
            console.close()
        if not writer:  # process 0 writes the report and prints the results
            return
        results = report.write(args.out, baseline=args.baseline)
    except experiment.RunError as err:
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
    print(f"\nmean iterations-to-success per task ({args.run.seeds} seeds):")
    for name, m in results["methods"].items():
        print(f"  {name:14s} {np.round(m['iterations_to_success_mean'], 1).tolist()}")
    best = results.get("best", {m: m for m in results["methods"]})
    if "best" in results:
        print("best grid point per method: " + ", ".join(best.values()))
    half = args.run.num_tasks // 2
    if half >= 1:
        later = {n: float(np.mean(np.asarray(results["methods"][n]["iterations_to_success"])[:, half:]))
                 for n in best.values()}
        print(f"mean over tasks {half + 1}-{args.run.num_tasks}: " +
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

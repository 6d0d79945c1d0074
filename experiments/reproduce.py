"""Reproduce a family's experiments of the paper: its methods on its sequences, as one study directory, reported
beside the paper's own numbers.

    python experiments/reproduce.py ant_goal                      # the CPU scale: CoMPS, GMPS+PPO(+IS), PPO+TL, 6 tasks
    python experiments/reproduce.py ant_goal --scale paper        # 6 methods x 2 sequences x 40 tasks x 6 seeds
    python experiments/reproduce.py ant_goal --out ~/studies/ag --resume     # continue every method where it stopped
    python experiments/reproduce.py ant_goal --out ~/studies/ag --partial    # report what is finished so far
    python experiments/reproduce.py cheetah_vel --scale paper --ablation --parallel 2 --wandb jcomps

Each method of each sequence is a ``run_sequence.py`` run of its own (``OUT/<sequence>/<method>/``, its log in
``OUT/logs/``), run in turn or ``--parallel N`` at a time, with the same device count (the study's, chosen when it
starts: one per core divided among the parallel runs). When they have finished, each sequence's runs are merged
(``OUT/<sequence>/merged/``, as ``merge_runs.py`` does) and the study's report is written: ``OUT/report.md``
(the p-value table in the paper's format beside the paper's published p-values, the table of the paper's claims
with what this study shows for each), ``OUT/reproduction.json`` and ``OUT/figures/`` (the paper's Figure 3 panel,
the lifelong return). ``jcomps.analysis.reproduction`` has the protocols and the tables, ``jcomps.analysis.paper`` the
paper's numbers. Options after ``--`` go to every run (``-- --budget 300 --set comps.meta.outer_learning_rate=0.005``).
Bad options exit with code 2 naming the option.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import threading
import time

from jcomps import envs
from jcomps.analysis import paper, reproduction
from jcomps.console import clock
from jcomps.runner import files, hostdevices, results, rundir
from jcomps.runner.files import RunError

HERE = os.path.dirname(os.path.abspath(__file__))

STUDY = "study.json"
FORMAT = 1


def parse_args(argv=None):
    extra = []
    if argv is None:
        argv = sys.argv[1:]
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("family", help="the family (" + ", ".join(envs.names()) + "); the paper ran "
                        + ", ".join(paper.FAMILIES))
    parser.add_argument("--scale", choices=reproduction.SCALES, default=None,
                        help="cpu (default): CoMPS, GMPS+PPO, GMPS+PPO+IS and PPO+TL on the first 6 non-stationary "
                             "tasks, 4 seeds; paper: CoMPS, PPO+TL, GMPS+PPO, MAML+TL, PNC and PEARL on both sequences, 40 "
                             "tasks, 6 seeds (a GPU's or a cluster's)")
    parser.add_argument("--seeds", type=int, default=None, help="seeds per method (default: the scale's)")
    parser.add_argument("--num-tasks", type=int, default=None, help="tasks per sequence (default: the scale's)")
    parser.add_argument("--methods", nargs="+", default=None, help="the methods (default: the scale's; comps always)")
    parser.add_argument("--sequences", nargs="+", default=None, choices=reproduction.SEQUENCES,
                        help="the sequences (default: the scale's)")
    parser.add_argument("--ablation", action="store_true",
                        help="add the ladder's other rungs (gmps, gmps_ppo_is, gmps_ppo_is_x2)")
    parser.add_argument("--out", default=None, help="the study directory (default: runs/reproduce-<family>-<scale>)")
    parser.add_argument("--resume", action="store_true", help="continue the study in --out: every run where it "
                        "stopped (the stored protocol; options given again must agree with it)")
    parser.add_argument("--partial", action="store_true",
                        help="run nothing: report the tasks every method of each sequence has finished")
    parser.add_argument("--parallel", type=int, default=1, metavar="N", help="runs at a time (default 1)")
    parser.add_argument("--devices", type=int, default=None,
                        help="host devices of every run (default: the cores divided among --parallel runs; a "
                             "study keeps the count it started with)")
    parser.add_argument("--tensorboard", action="store_true", help="every run also writes TensorBoard logs")
    parser.add_argument("--wandb", default=None, metavar="PROJECT",
                        help="every run also logs to Weights & Biases (offline unless WANDB_MODE says otherwise; "
                             "the study's name is the runs' group)")
    parser.add_argument("--print-commands", action="store_true",
                        help="create the study (or take it, with --resume) and print each unfinished run's "
                             "run_sequence.py command instead of running it (to run them elsewhere, e.g. as SLURM "
                             "jobs; --partial then reports them)")
    args = parser.parse_args(argv)
    args.extra = extra
    if args.parallel < 1:
        parser.error(f"--parallel must be >= 1, got {args.parallel}")
    if args.devices is not None and not 1 <= args.devices <= hostdevices.cores():
        parser.error(f"--devices {args.devices}: allowed 1 to {hostdevices.cores()} (this machine's cores)")
    if (args.resume or args.partial) and not args.out:
        parser.error(("--resume" if args.resume else "--partial") + " needs --out, the study directory")
    try:
        args.study = _study(args)
    except (ValueError, RunError) as err:
        parser.error(str(err))
    return args


def _study(args) -> dict:
    """The study: {"protocol": Protocol, "devices": int} from --out's study.json (--resume, --partial) or the
    options (a new study)."""
    path = os.path.join(args.out, STUDY) if args.out else None
    if args.resume or args.partial:
        if not os.path.isfile(path):
            raise ValueError(f"{args.out} holds no study ({STUDY} missing); start it without --resume/--partial")
        try:
            stored = files.read_json(path)  # RunError (a ValueError) naming the file when it is not JSON
            proto = reproduction.Protocol.from_json(stored["protocol"])
            devices = int(stored["devices"])
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise ValueError(f"{path} is not a readable study ({err}); it is written by reproduce.py, start a new "
                             f"study in another --out") from err
        if proto.family != args.family:
            raise ValueError(f"{args.out} is a study of {proto.family}, not {args.family}")
        given = reproduction.protocol(args.family, args.scale or proto.scale, args.seeds, args.num_tasks,
                                      args.methods, args.sequences, args.ablation, tuple(args.extra))
        differ = [f for f, flag in (("scale", args.scale), ("seeds", args.seeds), ("num_tasks", args.num_tasks),
                                    ("methods", args.methods or args.ablation), ("sequences", args.sequences),
                                    ("extra", args.extra))
                  if flag and getattr(given, f) != getattr(proto, f)]
        if differ:
            raise ValueError(f"--resume: {', '.join(differ)} differ(s) from the study in {args.out} "
                             f"({', '.join(f'{f}={getattr(proto, f)}' for f in differ)}); give them as stored, or "
                             "start a new study in another --out")
        return {"protocol": proto, "devices": devices}
    proto = reproduction.protocol(args.family, args.scale or "cpu", args.seeds, args.num_tasks, args.methods,
                                  args.sequences, args.ablation, tuple(args.extra))
    args.out = args.out or os.path.join("runs", f"reproduce-{args.family}-{proto.scale}")
    if os.path.exists(os.path.join(args.out, STUDY)):
        raise ValueError(f"{args.out} already holds a study; continue it with --resume or choose another --out")
    devices = args.devices or max(1, hostdevices.cores() // args.parallel)
    return {"protocol": proto, "devices": devices}


def state(directory: str) -> str:
    """done (every entry's raw results written), started (a run.json) or new."""
    if not os.path.isfile(os.path.join(directory, "run.json")):
        return "new"
    try:
        description = rundir.read(directory)
        finished = all(results.load(directory, name) is not None for _, name, _ in description.entries())
    except RunError:
        return "started"
    return "done" if finished else "started"


def command(args, sequence: str, method: str) -> list[str]:
    """The ``run_sequence.py`` command of one run (``--resume`` where it has started)."""
    proto, out = args.study["protocol"], args.out
    directory = proto.run_directory(out, sequence, method)
    cmd = [sys.executable, os.path.join(HERE, "run_sequence.py"), *proto.run_options(sequence, method),
           "--out", directory, "--devices", str(args.study["devices"])]
    if state(directory) == "started":
        cmd.append("--resume")
    if args.tensorboard:
        cmd.append("--tensorboard")
    if args.wandb:
        cmd += ["--wandb", args.wandb, "--wandb-group", os.path.basename(os.path.abspath(out))]
    return cmd


def _pump(process, prefix: str, log_path: str, lock: threading.Lock) -> None:
    with open(log_path, "a") as log:
        for line in process.stdout:
            log.write(line)
            log.flush()
            with lock:
                print(prefix + line, end="", flush=True)


def run_all(args) -> list[tuple[str, str, int]]:
    """Runs every unfinished run, ``--parallel`` at a time; returns (sequence, method, exit code) of those that
    failed. A run refused for its options (exit code 2) stops the study from starting more."""
    proto = args.study["protocol"]
    todo = [(s, m) for s, m in proto.runs() if state(proto.run_directory(args.out, s, m)) != "done"]
    done = len(proto.runs()) - len(todo)
    print(f"study {args.out}: {len(proto.runs())} runs ({done} finished, {len(todo)} to run), "
          f"{args.study['devices']} device(s) each, {args.parallel} at a time", flush=True)
    os.makedirs(os.path.join(args.out, "logs"), exist_ok=True)
    lock, running, failed, began = threading.Lock(), [], [], time.time()
    previous = signal.signal(signal.SIGTERM, _interrupt)  # a kill stops the runs as Ctrl-C does
    try:
        _schedule(args, proto, todo, running, failed, lock, began)
    except KeyboardInterrupt:
        for _, method, process, _, _ in running:
            process.terminate()
        for sequence, method, process, pump, _ in running:
            process.wait()
            pump.join()
            failed.append((sequence, method, process.returncode))
        print(f"stopped: {len(running)} run(s) interrupted; `--out {args.out} --resume` continues them from their "
              "last checkpoints", file=sys.stderr, flush=True)
    finally:
        signal.signal(signal.SIGTERM, previous)
    return failed


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def _schedule(args, proto, todo, running, failed, lock, began) -> None:
    """Starts the runs of ``todo``, ``--parallel`` at a time, until every one has ended (``running``: those
    running; ``failed``: (sequence, method, exit code) of those that failed)."""
    stop = False
    while todo or running:
        while todo and len(running) < args.parallel and not stop:
            sequence, method = todo.pop(0)
            cmd = command(args, sequence, method)
            os.makedirs(os.path.dirname(proto.run_directory(args.out, sequence, method)), exist_ok=True)
            log_path = os.path.join(args.out, "logs", f"{sequence}-{method}.log")
            print(f"[{sequence}] starting {method}: {' '.join(cmd[1:])} (log: {log_path})", flush=True)
            process = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
            pump = threading.Thread(target=_pump, args=(process, f"[{sequence}] ", log_path, lock), daemon=True)
            pump.start()
            running.append((sequence, method, process, pump, log_path))
        if stop and not running:
            break
        time.sleep(0.5)
        for item in list(running):
            sequence, method, process, pump, log_path = item
            if process.poll() is None:
                continue
            pump.join()
            running.remove(item)
            if process.returncode == 0:
                print(f"[{sequence}] {method} finished ({clock(time.time() - began)} into the study)", flush=True)
            else:
                failed.append((sequence, method, process.returncode))
                print(f"error: [{sequence}] {method} stopped with exit code {process.returncode}; its log: "
                      f"{log_path}", file=sys.stderr, flush=True)
                stop = stop or process.returncode == 2
        if stop and todo:
            todo.clear()


def merge_sequence(args, sequence: str, partial: bool):
    """Merges the runs of ``sequence`` into ``OUT/<sequence>/merged`` (rewritten each time) and returns its
    results (None when CoMPS has nothing to report yet). With ``partial``, the runs with finished tasks."""
    from jcomps.analysis.merge import merge

    proto = args.study["protocol"]
    sources = []
    for method in proto.methods:
        directory = proto.run_directory(args.out, sequence, method)
        st = state(directory)
        if st == "done" or (partial and st == "started" and _has_partial(directory)):
            sources.append(directory)
        elif not partial:
            raise RunError(f"{directory} has not finished; continue the study with --resume, or report what is "
                           "finished with --partial")
    if proto.run_directory(args.out, sequence, "comps") not in sources:
        return None
    merged = os.path.join(args.out, sequence, "merged")
    if os.path.isdir(merged):
        shutil.rmtree(merged)  # derived from the runs: rewritten every time
    return merge(merged, sources, baseline="comps", partial=partial)


def _has_partial(directory: str) -> bool:
    description = rundir.read(directory)
    return all(results.load(directory, n) is not None or results.load_partial(directory, n) is not None
               for _, n, _ in description.entries())


def write_report(args, partial: bool) -> dict:
    """The study's report (report.md, reproduction.json, figures/) from the merged sequences."""
    proto = args.study["protocol"]
    by_sequence, cut = {}, {}
    for sequence in proto.sequences:
        merged = merge_sequence(args, sequence, partial)
        if merged is None:
            print(f"[{sequence}] nothing to report yet: CoMPS has not finished a task", flush=True)
            continue
        by_sequence[sequence] = merged
        if "partial" in merged:
            cut[sequence] = merged["partial"]
    if not by_sequence:
        raise RunError(f"{args.out}: no sequence has anything to report yet")
    text = reproduction.markdown(proto.family, proto, by_sequence, cut or None)
    figures = reproduction.figures(by_sequence, os.path.join(args.out, "figures"), proto.family)
    out = {"protocol": proto.to_json(), "partial": cut or None,
           "p_values": {s: reproduction.p_value_table(r, proto.family, s) for s, r in by_sequence.items()},
           "claims": reproduction.claims_table(by_sequence, proto.family),
           "figures": [os.path.relpath(p, args.out) for p in figures]}
    files.write_json(os.path.join(args.out, "reproduction.json"), out)
    with open(os.path.join(args.out, "report.md.tmp"), "w") as f:
        f.write(text)
    os.replace(os.path.join(args.out, "report.md.tmp"), os.path.join(args.out, "report.md"))
    print("\n" + text + f"\nreport, figures and merged runs in {args.out}/", flush=True)
    return out


def main(argv=None):
    args = parse_args(argv)
    proto = args.study["protocol"]
    try:
        if not args.partial:
            if not args.resume:
                os.makedirs(args.out, exist_ok=True)
                files.write_json(os.path.join(args.out, STUDY), {"format": FORMAT, "protocol": proto.to_json(),
                                                                  "devices": args.study["devices"]})
            if args.print_commands:
                for sequence, method in proto.runs():
                    if state(proto.run_directory(args.out, sequence, method)) != "done":
                        print(" ".join(command(args, sequence, method)[1:]))
                return
            failed = run_all(args)
            if failed:
                print(f"error: {len(failed)} run(s) did not finish: " + ", ".join(
                    f"{s}/{m} (exit {c})" for s, m, c in failed) + f". `--out {args.out} --resume` continues "
                    f"them; `--partial` reports what is finished", file=sys.stderr, flush=True)
                sys.exit(2 if any(c == 2 for _, _, c in failed) else 1)
        write_report(args, args.partial)
    except RunError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()

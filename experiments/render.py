"""Replay the checkpointed policies of a run and write a viewer per task, beside the run's plots.

    python experiments/render.py RUN_DIR [--method M ...] [--seed S] [--tasks I J ...] [--mean]

Without options: every method (every grid point) of the run, its first seed, the last task learnt. Tasks are
numbered from 1 as in the report and the progress lines; a task after the last one learnt shows the current policy
on a task it has not met yet. The policy is the one in the run's newest checkpoint (``params.policy``: the one the
method starts its next task from and the evaluations read; for CoMPS, the meta-trained policy), with its
observation normalisation; PEARL's acts on a learnt task with a latent drawn from the posterior of that task's
context (its replay buffer). It acts as it learnt and was measured, sampling from its distribution (``--mean``:
the mean action). ``--episodes`` episodes are run on the task (default: the method's trajectories per iteration); the
success rate printed is theirs, measured as the learner measures it, and the viewer shows the first.

MuJoCo families: an HTML page per task, ``RUN_DIR/render/<entry>_seed<S>_task<N>.html``, written by brax's own
renderer (``brax.io.html``: three.js in the browser, no OpenGL needed here). The page holds the whole episode but
fetches its scripts from the web when opened: three.js from unpkg.com and brax's viewer from cdn.jsdelivr.net
(``--base-url`` points the viewer elsewhere). Point Goal has no physics to show: a PNG of the episodes' paths and
the goal instead.
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from jcomps import continual, envs, methods
from jcomps.runner import checkpoint, distributed, members, rundir
from jcomps.runner import grid as grids
from jcomps.runner.description import RunDescription
from jcomps.runner.files import RunError


def _episodes(family, act, policy, task, rng, episodes: int, mean):
    """``episodes`` fresh episodes of ``task``: the first one's simulator states (T_max + 1), every reward, success
    indicator and whether the step was taken by a live episode [T, episodes] and the first two observation
    components [T + 1, episodes, 2]. ``act`` is the
    method's ``acting.ActFn``; ``mean`` (f32[], 0 or 1; traced, so both modes share one compilation) replaces the
    policy's noise by zeros (the mean action; PEARL's tanh of its mean)."""
    reset_rng, step_rng = jax.random.split(rng)
    state = jax.vmap(family.reset, (0, None))(jax.random.split(reset_rng, episodes), task)
    step = jax.vmap(family.step, (0, 0, None))

    def body(state, noise):
        action, _ = act(policy, state.obs, noise * (1.0 - mean))
        nxt = step(state, action, task)
        return nxt, (jax.tree.map(lambda x: x[0], nxt.sim), nxt.reward, nxt.success, 1.0 - state.done,
                     nxt.obs[:, :2])

    noise = jax.random.normal(step_rng, (family.max_steps, episodes, family.action_size), jnp.float32)
    _, (sims, rewards, success, valid, xy) = jax.lax.scan(body, state, noise)
    first = jax.tree.map(lambda x: x[0], state.sim)
    sims = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), first, sims)
    return sims, rewards, success, valid, jnp.concatenate([state.obs[None, :, :2], xy])


def _policies(run_dir: str, description: RunDescription, spec, warn):
    """The members' states of program ``spec`` from its newest checkpoint, and the number of tasks learnt."""
    run, family = description.run, description.family
    found = checkpoint.read_latest(os.path.join(run_dir, "checkpoints", spec.directory), warn)
    if found is None:
        raise RunError(f"{run_dir}: {spec.label} has no checkpoint yet (it writes one after every chunk "
                                  "of tasks)")
    _, tree = found
    _, member_seed, hparams = members.layout(spec, run.seeds, run.seed, description.devices)

    def make(h):
        return methods.make(spec.method, family, grids.with_traced(spec.config, h) if h else spec.config)

    keys = members.method_keys(member_seed)
    if spec.traced:
        shapes = jax.eval_shape(lambda k, h: continual.init_seeds(make, k, h), keys, hparams)
    else:
        shapes = jax.eval_shape(lambda k: continual.init_seeds(make({}), k), keys)
    like = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), shapes)
    states = checkpoint.unflatten(like, tree["states"])
    chunk = min((description.chunk_tasks_by_method or {}).get(spec.method, run.chunk_tasks), run.num_tasks)
    learnt = min(int(tree["counters"]["next_chunk"]) * chunk, run.num_tasks)
    return states, learnt


def _plot_point_goal(path, xy, goal, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 5))
    for e in range(xy.shape[1]):
        ax.plot(xy[:, e, 0], xy[:, e, 1], lw=0.8, alpha=0.6)
    ax.add_patch(plt.Circle(goal, 0.2, color="k", fill=False, lw=1.5, label="goal (success radius 0.2)"))
    ax.plot([0], [0], "k+", label="start")
    ax.set_aspect("equal")
    ax.set_xlim(-2.6, 2.6)
    ax.set_ylim(-2.6, 2.6)
    ax.set_title(title, fontsize=9)
    ax.legend(loc="lower right", fontsize=8)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def render(run_dir: str, methods_=None, seed=None, tasks=None, mean=False, episodes=None, base_url=None,
           out_dir=None, print_fn=print) -> list[str]:
    """Writes the viewers (see the module docstring); returns their paths."""
    description = rundir.read(run_dir)
    run, family = description.run, description.family
    if family.host_rollout is not None:
        raise RunError("render.py draws the MJX families with brax's viewer and Point Goal as a plot; "
                                  "MetaWorld runs on MuJoCo's C library, whose renderer needs OpenGL, and has no "
                                  "replay here yet")
    specs = {m: description.programs(m) for m in run.methods}
    chosen = methods_ or run.methods
    for m in chosen:
        if m not in specs:
            raise RunError(f"--method {m}: not a method of this run; its methods: {', '.join(specs)}")
    seed = run.seed if seed is None else seed
    if seed not in run.seed_list:
        raise RunError(f"--seed {seed}: the run's seeds are {run.seed}..{run.seed_list[-1]}")
    for t in tasks or ():
        if not 1 <= t <= run.num_tasks:
            raise RunError(f"--tasks {t}: tasks are numbered 1..{run.num_tasks} in this run")
    values = envs.sequence_values(family, run.sequence, seed, run.num_tasks, run.tasks)
    out_dir = out_dir or os.path.join(run_dir, "render")
    os.makedirs(out_dir, exist_ok=True)
    warn = lambda message: print_fn(f"warning: {message}")  # noqa: E731
    unit = family.value_unit
    episode_fn = jax.jit(_episodes, static_argnums=(0, 1, 5))
    written = []
    for m in chosen:
        config = specs[m][0].config
        n_episodes = episodes or methods.collection(config).num_trajectories
        method = methods.make(m, family, config)
        act = method.actor.act
        for spec in specs[m]:
            states, learnt = _policies(run_dir, description, spec, warn)
            if learnt == 0:
                raise RunError(f"{run_dir}: {spec.label} has learnt no task yet")
            for p, point in enumerate(spec.points):
                member = p * run.seeds + (seed - run.seed)
                state = jax.tree.map(lambda x: jnp.asarray(x[member]), states)
                for t in tasks or [learnt]:
                    task = envs.task_at(family, t - 1, run.sequence, seed, run.tasks)
                    rng = jax.random.fold_in(jax.random.PRNGKey(seed), t)
                    # the policy for task t (PEARL's latent from task t's replay buffer); a task not learnt yet
                    # meets the policy after the last one learnt
                    policy = (methods.base.policy_for(method, state, jnp.int32(t - 1), task,
                                                        jax.random.fold_in(rng, 1))
                              if t <= learnt else state.params.policy)
                    sims, rewards, success, valid, xy = episode_fn(family, act, policy, task, rng, n_episodes,
                                                            jnp.float32(mean))
                    rate = float(family.success_rate(success, valid))
                    ret = float(jnp.mean(jnp.sum(rewards, axis=0)))
                    note = "" if t <= learnt else f", not learnt yet (the policy after task {learnt})"
                    title = (f"{point.key}, seed {seed}, task {t} ({values[t - 1]:g} {unit}){note}: success rate "
                             f"{rate:.2f} over {n_episodes} episodes (threshold {family.success_threshold:g}), "
                             f"mean return {ret:.1f}")
                    name = f"{point.key}_seed{seed}_task{t:02d}".replace("=", "-").replace(",", "_")
                    if family.system is None:
                        path = os.path.join(out_dir, name + ".png")
                        _plot_point_goal(path, np.asarray(xy), np.asarray(task.goal), title)
                    else:
                        from brax.io import html

                        sims = jax.device_get(sims)
                        states = [jax.tree.map(lambda x: x[i], sims) for i in range(family.max_steps + 1)]
                        page = html.render(family.system, states, height="80vh", colab=False, base_url=base_url)
                        page = page.replace("<body>", f"<body><p style='font-family:sans-serif'>{title}; the "
                                            "first episode is shown</p>", 1)
                        path = os.path.join(out_dir, name + ".html")
                        with open(path, "w") as f:
                            f.write(page)
                    print_fn(f"{title} -> {path}")
                    written.append(path)
    return written


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="a directory written by experiments/run_sequence.py")
    parser.add_argument("--method", nargs="+", default=None, help="methods to show (default: all of the run's)")
    parser.add_argument("--seed", type=int, default=None, help="which seed (default: the run's first)")
    parser.add_argument("--tasks", type=int, nargs="+", default=None,
                        help="task numbers, from 1 (default: the last task learnt)")
    parser.add_argument("--mean", action="store_true", help="act with the policy's mean instead of sampling")
    parser.add_argument("--episodes", type=int, default=None,
                        help="episodes run per task for the success rate (default: the method's trajectories per "
                             "iteration); the first is shown")
    parser.add_argument("--base-url", default=None,
                        help="where the page loads brax's viewer.js from (default: brax's release on the "
                             "jsDelivr CDN)")
    parser.add_argument("--out", default=None, help="where to write (default: RUN_DIR/render)")
    distributed.add_args(parser)
    args = parser.parse_args(argv)
    if not distributed.tool_process(args, parser):
        return
    if args.episodes is not None and args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    try:
        render(args.run_dir, args.method, args.seed, args.tasks, args.mean, args.episodes, args.base_url, args.out)
    except RunError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()

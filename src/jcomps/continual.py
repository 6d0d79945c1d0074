"""The continual protocol: a method learns a sequence of tasks one at a time, and is evaluated as it goes.

The pieces the runner (``jcomps.runner.experiment``) compiles, each a pure function of one member's state:
``learn_at`` learns the task at one position of the sequence; ``evaluate_task`` evaluates the state right after
it (backward transfer on the previous tasks, the learnt task itself); ``heldout_adaptation`` is the held-out
meta-test and ``learnt_tasks`` evaluates the policy on every task learnt so far (forgetting, average performance),
with the same episodes of each task as right after it was learnt. The runner's host loop runs them task by task,
chunk by chunk, with a checkpoint after every chunk.

For library use without a run directory, ``run_tasks`` learns a whole sequence as one ``lax.scan`` over tasks and
``run_seeds`` vmaps it over seeds: one compiled program, no evaluations.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp

from jcomps import envs, progress
from jcomps.methods import base
from jcomps.methods.base import Method, TaskMetrics
from jcomps.numerics import check_field, check_finite_fields, concrete_max
from jcomps.progress import ProgressFn, with_fields
from jcomps.training import acting, ppo, rl_loop


def check_capacity(method: Method, num_tasks: int, start=0) -> None:
    """Raises ValueError if learning ``num_tasks`` tasks from task index ``start`` would pass the method's
    ``max_tasks`` (its experience-store slots): the stores would otherwise silently overwrite their last slot.
    A traced ``start`` is not checked (the sequence length still is)."""
    max_tasks = base.task_slots(method.config)
    if max_tasks is None:
        return
    first = concrete_max(start) or 0
    if first + num_tasks > max_tasks:
        raise ValueError(f"invalid config value max_tasks={max_tasks}; allowed: at least the tasks learnt "
                         f"({first} + {num_tasks}): {method.name} keeps one experience slot per task")


def run_tasks(method: Method, state: Any, tasks, progress_fn: Optional[ProgressFn] = None):
    """Learns ``tasks`` (a task pytree with a leading task axis) in order, starting from ``state``.

    ``learn_task`` is wrapped in ``jax.jit`` so that it is traced once per method and shapes, however long the
    sequence and however it is chunked. ``progress_fn`` (``jcomps.progress``), if given, gets ``{"task",
    "task_iterations", "solved"}`` after each task. Returns (final state, TaskMetrics with a leading task axis).
    """
    check_capacity(method, jax.tree.leaves(tasks)[0].shape[0], state.task_index)
    learn = jax.jit(method.learn_task)

    def body(state, task):
        new_state, metrics = learn(state, task)
        if progress_fn is not None:
            progress_fn({"phase": progress.TASK, "task": state.task_index, "task_iterations": metrics.iterations,
                         "solved": metrics.solved})
        return new_state, metrics

    return jax.lax.scan(body, state, tasks)


def run_sequence(method: Method, tasks, rng: jax.Array, progress_fn: Optional[ProgressFn] = None):
    """``method.init(rng)`` then ``run_tasks``; returns (final state, TaskMetrics[num_tasks])."""
    return run_tasks(method, method.init(rng), tasks, progress_fn)


def init_seeds(method: Method, rngs: jax.Array, hparams: Optional[dict] = None):
    """``method.init`` for each of the S keys ``rngs``, stacked (leading seed axis). Jittable.

    One seed at a time (``lax.map``), not under ``vmap``: a batched QR (the orthogonal initialisers) is jaxlib's
    LAPACK kernel splitting the batch over XLA:CPU's intra-op thread pool and waiting for the parts on a pool
    thread; several at once can occupy every pool thread and wait forever (seen with jax 0.10.2 on 2 host
    devices: gdb shows both "tf_XLAEigen" threads in ParallelBatchMap under QrFactorization; see
    ``jcomps.runner.hostdevices``). Unbatched, the kernel runs inline; the values are the same.

    With ``hparams`` (a dict of arrays with a leading axis of S, a hyperparameter grid's traced values per
    member), ``method`` is instead a function of one member's dict of scalars that makes its Method, called
    inside the map, so each member is initialised with its own values (``init_std``), still one at a time.
    """
    if hparams is None:
        return jax.lax.map(method.init, rngs)
    return jax.lax.map(lambda x: method(x[1]).init(x[0]), (rngs, hparams))


def run_seeds(method: Method, tasks, rngs: jax.Array, progress_fn: Optional[ProgressFn] = None,
              tasks_per_seed: bool = False):
    """``run_sequence`` vmapped over ``rngs`` (a batch of S keys), jitted as one program.

    ``tasks`` is shared by all seeds, or, with ``tasks_per_seed``, has a leading seed axis (stationary
    sequences shuffled per seed). ``progress_fn`` gets each seed's per-task metrics with its index ``seed``
    added. Returns (states, TaskMetrics) with a leading seed axis.
    """
    def run(tasks, rngs, seed_index):
        states = init_seeds(method, rngs)
        fn = jax.vmap(lambda t, s, i: run_tasks(method, s, t, with_fields(progress_fn, seed=i)),
                      in_axes=(0 if tasks_per_seed else None, 0, 0))
        return fn(tasks, states, seed_index)

    return jax.jit(run)(tasks, rngs, jnp.arange(rngs.shape[0], dtype=jnp.int32))


LEARNT_EVAL = ("chunk", "end")
"""When ``learnt_tasks`` runs (``EvalConfig.learnt_eval``): after every chunk, or after the last task only."""


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Evaluations made while a sequence runs (they never change what the method learns)."""

    backward_tasks: int = 3
    """After each task, the policy is evaluated on this many previous tasks (backward transfer); 0: off."""
    heldout_iterations: int = 0
    """Length of the held-out return curve: PPO iterations of adaptation on each held-out task, from the current
    policy, after every chunk (no learning is kept); 0, the default: the held-out meta-test is off but for the
    zero-shot return (entry 0 of the curve, one batch per held-out task). SPEC asks for "a fixed small adaptation
    budget" and the paper gives none (L258); ours is 5 when on (``--heldout-iterations 5``); on the first tasks of a sequence it says little (docs/results.md, "The held-out
    meta-test"), and the studies that measure it ask for it."""
    heldout_budget: Optional[int] = None
    """Cap of the held-out iterations-to-success (on tasks never trained on): the same adaptation runs up to this
    many iterations (at least ``heldout_iterations`` + 1); 0: not measured; none: the family's default when the
    held-out curve is on (``heldout_iterations`` > 0; its ``"eval"`` settings in ``jcomps.envs``: 50 on
    point_goal, 0 on the MuJoCo families and MetaWorld), else 0."""
    learnt_eval: str = "chunk"
    """When the policy is evaluated on every task learnt so far (success rate and return: forgetting, average
    performance): chunk (after every chunk of tasks) or end (after the last task only). Each task is also
    evaluated right after it is learnt, with the same episodes."""
    learnt_episodes: int = 0
    """Fresh episodes of every evaluation of a learnt task (right after it is learnt and by learnt_eval); 0: the
    method's episodes per iteration (num_trajectories)."""

    def __post_init__(self):
        check_finite_fields(self)
        check_field(self.backward_tasks >= 0, "backward_tasks", self.backward_tasks, "an integer >= 0")
        check_field(self.heldout_iterations >= 0, "heldout_iterations", self.heldout_iterations,
                        "an integer >= 0")
        check_field(self.heldout_budget is None or self.heldout_budget >= 0, "heldout_budget", self.heldout_budget,
                    "an integer >= 0 (0: off) or none (the family's default)")
        check_field(self.learnt_eval in LEARNT_EVAL, "learnt_eval", self.learnt_eval, ", ".join(LEARNT_EVAL))
        check_field(self.learnt_episodes >= 0, "learnt_episodes", self.learnt_episodes,
                    "an integer >= 0 (0: the method's num_trajectories)")

    def resolve(self, family: str) -> "EvalConfig":
        """This config with the family's defaults filled in (``heldout_budget``: from its ``"eval"`` settings in
        ``jcomps.envs`` when the held-out curve is on, else 0): what a run uses and records."""
        if self.heldout_budget is not None:
            return self
        budget = envs.settings(family, "eval").get("heldout_budget", 0) if self.heldout_iterations > 0 else 0
        return dataclasses.replace(self, heldout_budget=budget)

    @property
    def heldout_measured(self) -> bool:
        """Whether the held-out meta-test adapts (a curve beyond the zero-shot return, or iterations-to-success)."""
        return self.heldout_iterations > 0 or bool(self.heldout_budget)

    @property
    def heldout_run(self) -> int:
        """Iterations of each held-out adaptation run."""
        if self.heldout_budget is None:
            raise ValueError("EvalConfig.heldout_budget is none: resolve the config for a family first "
                             "(EvalConfig.resolve)")
        return max(self.heldout_iterations + 1, self.heldout_budget)

    def episodes(self, method: Method) -> int:
        """Episodes of each evaluation of a learnt task of ``method``."""
        return self.learnt_episodes or base.collection(method.config).num_trajectories


class Evaluation(NamedTuple):
    """Fresh episodes of a policy on tasks (leading axes where used).

    Attributes:
      mean_return: f32, mean episode return.
      success_rate: f32, the family's success rate of the episodes (``Family.success_rate``).
      valid: bool, False where nothing was evaluated (then both values are 0).
    """

    mean_return: jax.Array
    success_rate: jax.Array
    valid: jax.Array


class ChunkMetrics(NamedTuple):
    """What the runner reports for the task positions of a chunk (leading axis [chunk]): each position's
    ``learn_at`` metrics and ``evaluate_task`` evaluations (``chunk_metrics``).

    Attributes:
      task: TaskMetrics of each task learnt.
      backward_returns: f32[chunk, backward_tasks], mean episode return of the policy after task i on task
        i − 1 − d (d = 0 … backward_tasks − 1), with ``num_trajectories`` fresh episodes.
      backward_valid: bool[chunk, backward_tasks], False where i − 1 − d < 0 or the position is past the end.
      backward_success: f32[chunk, backward_tasks], the success rate of the same episodes.
      learnt: Evaluation [chunk], the policy right after task i on task i itself, with the episodes of task i
        that every ``learnt_tasks`` evaluation uses (the start of its forgetting).
    """

    task: TaskMetrics
    backward_returns: jax.Array
    backward_valid: jax.Array
    backward_success: Optional[jax.Array] = None
    learnt: Optional[Evaluation] = None


# The evaluations of a learnt task j descend from ``fold_in(eval_key, LEARNT_SALT)`` folded with j, apart from the
# backward-transfer keys ``fold_in(fold_in(eval_key, i), d)`` (i a task position, far below the salt).
LEARNT_SALT = 0x6C726E74  # "lrnt"


def learnt_key(eval_key, j):
    """The key of every evaluation of the task at position ``j`` as a learnt task: right after it is learnt and
    at every ``learnt_tasks`` evaluation. The same episodes each time (common random numbers), so a policy that
    does not change scores the same and its forgetting is exactly 0."""
    return jax.random.fold_in(jax.random.fold_in(eval_key, LEARNT_SALT), j)


def _evaluate(method: Method, state, slot, task, key, episodes: int):
    """(mean return, success rate) of ``episodes`` fresh episodes on ``task`` (learnt in ``slot``) of the policy
    ``base.policy_for`` gives; the rollout draws from ``key``, the policy (MAML+TL's adaptation) from its fold 7."""
    policy = base.policy_for(method, state, slot, task, jax.random.fold_in(key, 7))
    traj = acting.rollout(method.family, policy, task, key, episodes, actor=method.actor)
    return rl_loop.episode_stats(method.family, traj)


def _task_at(sequence, i):
    return jax.tree.map(lambda x: jax.lax.dynamic_index_in_dim(x, i, keepdims=False), sequence)


def learn_at(method: Method, state, sequence, i):
    """Learns the task at position ``i`` (i32[]) of ``sequence`` (a task pytree [num_tasks]) from ``state``:
    (state, TaskMetrics). The runner's ``learn`` program (one task; the host loops over positions). A sequence
    longer than the method's task slots is refused (``check_capacity``)."""
    check_capacity(method, jax.tree.leaves(sequence)[0].shape[0])
    return jax.jit(method.learn_task)(state, _task_at(sequence, i))


class TaskEvaluation(NamedTuple):
    """The evaluations right after the task at position i is learnt (``evaluate_task``); the fields of
    ``ChunkMetrics`` of that position but ``task``."""

    backward_returns: jax.Array
    backward_valid: jax.Array
    backward_success: jax.Array
    learnt: Evaluation


def evaluate_task(method: Method, eval_config: EvalConfig, state, sequence, i, eval_key) -> TaskEvaluation:
    """The evaluations of ``state``, the state right after learning the task at position ``i`` (i32[]) of
    ``sequence``: backward transfer on the ``eval_config.backward_tasks`` previous tasks (fresh episodes from
    ``fold_in(fold_in(eval_key, i), d)``) and the learnt task itself (``learnt_key``). Nothing is kept. The
    runner's ``evaluate_task`` program, run after each ``learn`` program."""
    k = eval_config.backward_tasks
    trajectories = base.collection(method.config).num_trajectories
    prev = i - 1 - jnp.arange(k)
    keys = jax.vmap(lambda d: jax.random.fold_in(jax.random.fold_in(eval_key, i), d))(jnp.arange(k))

    def back(j, key):
        j = jnp.maximum(j, 0)  # every task's rollout draws from its own ``key``
        return _evaluate(method, state, j, _task_at(sequence, j), key, trajectories)

    # Two rollouts, not one of k + 1 lanes: XLA rounds a lane's mean return differently in a batch of another size,
    # and the learnt task's evaluation must equal learnt_tasks' on the same policy bit for bit (forgetting 0).
    returns, success = jax.vmap(back)(prev, keys)
    now = _evaluate(method, state, i, _task_at(sequence, i), learnt_key(eval_key, i), eval_config.episodes(method))
    return TaskEvaluation(returns, prev >= 0, success, Evaluation(*now, jnp.bool_(True)))


def chunk_metrics(metrics: TaskMetrics, evaluation: TaskEvaluation) -> ChunkMetrics:
    """The ChunkMetrics of one position from its TaskMetrics and TaskEvaluation."""
    return ChunkMetrics(metrics, evaluation.backward_returns, evaluation.backward_valid, evaluation.backward_success,
                        evaluation.learnt)


def learnt_tasks(method: Method, eval_config: EvalConfig, state, sequence, learnt, eval_key) -> Evaluation:
    """The policy of ``state`` on every task of ``sequence`` (a task pytree [num_tasks]) learnt so far, the
    positions below ``learnt`` (i32[], must not be batched): Evaluation [num_tasks], with the episodes of
    ``learnt_key(eval_key, j)`` (those of ``ChunkMetrics.learnt``); the other positions are skipped (a
    ``lax.cond``: the cost grows with the tasks learnt) and report zeros, valid False. Nothing is kept."""
    num_tasks = jax.tree.leaves(sequence)[0].shape[0]
    episodes = eval_config.episodes(method)

    def one(j):
        def do(_):
            task = _task_at(sequence, j)
            return Evaluation(*_evaluate(method, state, j, task, learnt_key(eval_key, j), episodes), jnp.bool_(True))

        shapes = jax.eval_shape(do, None)
        skip = lambda _: jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)  # noqa: E731
        return jax.lax.cond(j < learnt, do, skip, None)

    return jax.lax.map(one, jnp.arange(num_tasks, dtype=jnp.int32))


class HeldoutMetrics(NamedTuple):
    """Held-out meta-test of one policy (``heldout_adaptation``); leading axis [num_heldout].

    Attributes:
      mean_return, success_rate: f32[num_heldout, heldout_iterations + 1]; entry 0 is the policy as it is
        (zero-shot), entry n the policy after n PPO iterations.
      iterations: i32[num_heldout], iterations-to-success within ``heldout_run`` iterations (that cap if never
        reached; 0 when ``heldout_budget`` is 0).
      solved: bool[num_heldout], whether the threshold was reached within the cap.
    """

    mean_return: jax.Array
    success_rate: jax.Array
    iterations: jax.Array
    solved: jax.Array


def _shape(*shape, dtype=jnp.float32):
    return jax.ShapeDtypeStruct(shape, dtype)


class Measurement(NamedTuple):
    """What the runner measures at the start and after every chunk of tasks: the held-out meta-test
    (``heldout_adaptation``) and the evaluation of every learnt task (``learnt_tasks``)."""

    heldout: HeldoutMetrics
    learnt: Evaluation


def heldout_shapes(eval_config: EvalConfig, num_heldout: int, num_tasks: int) -> Measurement:
    """The shapes (``jax.ShapeDtypeStruct``) of one member's Measurement without tracing ``heldout_adaptation``
    and ``learnt_tasks`` (the runner needs them before those programs are compiled; a test checks them against the
    traced functions)."""
    curve = eval_config.heldout_iterations + 1
    held = HeldoutMetrics(_shape(num_heldout, curve), _shape(num_heldout, curve), _shape(num_heldout, dtype=jnp.int32),
                          _shape(num_heldout, dtype=bool))
    return Measurement(held, Evaluation(_shape(num_tasks), _shape(num_tasks), _shape(num_tasks, dtype=bool)))


def task_evaluation_shapes(eval_config: EvalConfig) -> TaskEvaluation:
    """The shapes of one member's ``evaluate_task`` output, without tracing it."""
    k = eval_config.backward_tasks
    return TaskEvaluation(_shape(k), _shape(k, dtype=bool), _shape(k),
                          Evaluation(_shape(), _shape(), _shape(dtype=bool)))


def heldout_adaptation(method: Method, eval_config: EvalConfig, state, heldout_tasks, rng,
                       progress_fn: Optional[ProgressFn] = None) -> HeldoutMetrics:
    """Meta-test: PPO from the state's policy on every held-out task for ``eval_config.heldout_run`` iterations
    (stopping early only once the return curve is complete and the task solved), nothing kept (the state is not
    changed): the return curve and iterations-to-success. A method with its own meta-test (``Method.adapt``;
    PEARL's adapts by inference) runs that instead of PPO. ``progress_fn``, if given, gets the PPO adaptation's
    ``{"heldout_task", "heldout_iteration", "success_rate", "mean_return"}`` after every iteration."""
    eval_config = eval_config.resolve(method.family.name)
    curve = eval_config.heldout_iterations + 1
    measured = eval_config.heldout_budget > 0
    n = jax.tree.leaves(heldout_tasks)[0].shape[0]
    if method.adapt is not None:
        def own(task, key):
            returns, success = method.adapt(state, task, key, eval_config.heldout_run)
            first, solved = rl_loop.first_success(success, method.family.success_threshold, eval_config.heldout_run)
            return HeldoutMetrics(returns[:curve], success[:curve], jnp.where(measured, first, 0).astype(jnp.int32),
                                  solved & measured)

        return jax.vmap(own)(heldout_tasks, jax.random.split(rng, n))
    config = method.config.ppo
    optimizer = ppo.make_optimizer(config)
    params = state.params._replace(policy=config.task_start(state.params.policy))  # a held-out task is a new task

    def one(task, key, j):
        report = None
        if progress_fn is not None:
            report = lambda m: progress_fn({"phase": progress.HELDOUT_ITERATION, "heldout_task": j,  # noqa: E731
                                            "heldout_iteration": m["iteration"], "success_rate": m["success_rate"],
                                            "mean_return": m["mean_return"], "active": m["active"]})
        # Iterations after the curve's end and after the first success change nothing reported: left unrun.
        out = ppo.rl_step(config, method.family, params, optimizer.init(params), task, key, stop_at_threshold=False,
                          budget=eval_config.heldout_run, run_at_least=curve, progress_fn=report)
        return HeldoutMetrics(out.metrics.mean_return[:curve], out.metrics.success_rate[:curve],
                              jnp.where(measured, out.iterations, 0).astype(jnp.int32), out.solved & measured)

    return jax.vmap(one)(heldout_tasks, jax.random.split(rng, n), jnp.arange(n, dtype=jnp.int32))

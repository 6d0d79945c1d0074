"""Progress hooks: one signature for every part of jcomps.

A ``ProgressFn`` is called *inside* compiled code with a dict of scalar arrays, the way brax hands its
``progress_fn`` a metrics dict; what it does with them is its business (``host`` makes one that hands them to a
host function through ``jax.debug.callback``). Every dict says what it reports in ``phase`` (a Python string, the
one entry that is not an array; ``host`` passes it through unchanged), and carries:

- ``ITERATION``, after every RL iteration (``rl_loop.iterate``: PPO, MAML+TL, PEARL): ``iteration``,
  ``success_rate``, ``mean_return``, ``value_ev`` (the critic's explained variance of its value targets, measured
  by the iteration's update; NaN without one);
- ``META_STEP``, after every outer update of a meta-training phase (``meta.meta_train``): ``meta_step``,
  ``meta_steps``, ``bc_loss``, and the meta step's health as means over the seen tasks: ``value_l2``, ``value_ev``
  (the value heads' explained variance of the returns), ``adv_abs`` (mean |Â| of the inner step), ``rho`` (mean
  clipped importance weight), ``inner_gain`` (the outer loss before the inner step minus after it);
- ``COMPRESS_ITERATION``, after every iteration of a compress phase (``pnc``): ``compress_iteration``,
  ``compress_iterations``, ``kl``;
- methods add ``task`` (the index of the task being learnt) to all of these;
- ``HELDOUT_ITERATION``, after every iteration of a held-out adaptation (``continual.heldout_adaptation``):
  ``heldout_task``, ``heldout_iteration``, ``success_rate``, ``mean_return``;
- ``TASK``, after every task of the continual loop (``continual.run_tasks``): ``task``, ``task_iterations``,
  ``solved``.

``ITERATION`` and ``HELDOUT_ITERATION`` also carry ``active``: False where the call comes from a member whose loop
has stopped (a vmapped ``while_loop`` runs its body for every member until all have stopped, and discards the
stopped members' results); ``host`` drops those calls.

Because the hook runs at trace level, a caller can close it over traced values of its own (the runner closes it
over each member's index under ``vmap``) without the methods knowing about members.
"""

from __future__ import annotations

from typing import Callable, Optional

import jax

ProgressFn = Callable[[dict], None]

ITERATION = "iteration"
META_STEP = "meta_step"
COMPRESS_ITERATION = "compress_iteration"
HELDOUT_ITERATION = "heldout_iteration"
TASK = "task"
PHASES = (ITERATION, META_STEP, COMPRESS_ITERATION, HELDOUT_ITERATION, TASK)


def host(fn: Callable[[dict], None]) -> ProgressFn:
    """A ProgressFn that calls the host function ``fn(metrics)`` with numpy values (``jax.debug.callback``;
    under ``vmap`` once per batch element, in no fixed order); string entries (``phase``) are passed as they are.
    Calls whose ``active`` is False (a stopped member's) are dropped; ``active`` itself is not passed on."""
    def call(metrics: dict) -> None:
        static = {k: v for k, v in metrics.items() if isinstance(v, str)}
        arrays = {k: v for k, v in metrics.items() if not isinstance(v, str)}

        def send(values):
            if values.pop("active", True):
                fn({**static, **values})

        jax.debug.callback(send, arrays)

    return call


def with_fields(progress_fn: Optional[ProgressFn], **fields) -> Optional[ProgressFn]:
    """``progress_fn`` with ``fields`` (arrays) added to every metrics dict; None stays None."""
    if progress_fn is None:
        return None
    return lambda metrics: progress_fn({**fields, **metrics})

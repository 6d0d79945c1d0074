"""How well PPO's critic fits its returns: PPO+TL on the first tasks of a family, one line per task and case.

For each case (the family's default PPO config with ``--set`` overrides), PPO+TL learns the first ``--tasks``
tasks of the family's non-stationary sequence for ``--seeds`` seeds (one vmapped program), and after each task the
line gives the iterations to success, the critic's explained variance of its value targets (the GAE λ-returns,
measured on each iteration's batch before its update: the mean over the task's updates and the last), its value
loss, and the state of the critic's tanh layers on fresh episodes of the task with the final policy: the median
|pre-activation| and the share of units saturated (|pre-activation| > 3, where tanh' < 0.01) on at least 95% of
the states, per hidden layer; and the spread of the critic's outputs against the spread of the returns it should
predict (``v_std / ret_std``: 0 for a critic that predicts one constant), and the policy's entropy at the task's
end. The last line of a case averages its tasks.

    python benchmarks/critic_fit.py --family point_goal --tasks 3 --seeds 4
    python benchmarks/critic_fit.py --family point_goal --tasks 3 --seeds 4 --set reward_scale=0.1 --case scaled

Output: ``key=value`` pairs, one line per (case, task) and a summary line per case (``task=all``).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import typing

import jax
import jax.numpy as jnp
import numpy as np

from jcomps import envs, methods
from jcomps.analysis import statistics
from jcomps.configs import parse_value
from jcomps.numerics import masked_var
from jcomps.runner import hostdevices
from jcomps.training import acting, networks, ppo, vtrace


def parse_sets(items: list[str]) -> dict:
    """``FIELD=VALUE`` words as PPOConfig changes, each value parsed as its field's type."""
    hints = typing.get_type_hints(ppo.PPOConfig)
    out = {}
    for item in items:
        key, _, value = (x.strip() for x in item.partition("="))
        if key not in hints:
            raise SystemExit(f"--set {item}: unknown PPOConfig field {key!r}")
        out[key] = parse_value(hints[key], value)
    return out


def critic_state(params: networks.ActorCriticParams, obs: jax.Array, returns: jax.Array, valid: jax.Array):
    """Per hidden layer: median |pre-activation| and the share of units saturated on ≥ 95% of the valid states;
    and std(V) / std(returns) over the valid states."""
    x = networks.normalize_obs(params.policy, obs.reshape(-1, obs.shape[-1]))
    mask = valid.reshape(-1) > 0
    med, sat = [], []
    for layer in params.value[:-1]:
        pre = x @ layer["w"] + layer["b"]
        absval = jnp.abs(pre)
        med.append(jnp.nanmedian(jnp.where(mask[:, None], absval, jnp.nan)))
        saturated_share = jnp.sum((absval > 3.0) & mask[:, None], axis=0) / jnp.maximum(jnp.sum(mask), 1)
        sat.append(jnp.mean(saturated_share >= 0.95))
        x = jnp.tanh(pre)
    v = (x @ params.value[-1]["w"] + params.value[-1]["b"])[..., 0]
    std = lambda y: jnp.sqrt(masked_var(y, mask.astype(jnp.float32)))  # noqa: E731
    return jnp.stack(med), jnp.stack(sat), std(v) / jnp.maximum(std(returns.reshape(-1)), 1e-8)


def run_case(family, args, sets: dict, name: str) -> list[dict]:
    base = methods.default_config("ppo_tl", family)
    config = dataclasses.replace(base, ppo=dataclasses.replace(base.ppo, **sets))
    method = methods.make("ppo_tl", family, config)
    pcfg = config.ppo
    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.seeds)
    learn = jax.jit(jax.vmap(method.learn_task, in_axes=(0, None)))

    @jax.jit
    def inspect(params, task, rng):
        def one(p, k):
            traj = acting.rollout(family, p.policy, task, k, pcfg.num_trajectories)
            # The truncated discounted reward-to-go (no bootstrap at T_max), in the critic's reward units.
            ret = vtrace.discounted_returns(traj.reward * pcfg.reward_scale, pcfg.discount * (1.0 - traj.done),
                                            jnp.zeros(traj.reward.shape[1:]))
            return critic_state(p, traj.obs, ret, traj.valid)
        return jax.vmap(one)(params, jax.random.split(rng, args.seeds))

    state = jax.vmap(method.init)(keys)
    rows, t0 = [], time.time()
    for i in range(args.tasks):
        task = envs.task_at(family, i)
        state, metrics = learn(state, task)
        per_it = metrics.per_iteration
        fit = statistics.critic_fit(np.asarray(per_it.value_ev)[:, None], np.asarray(per_it.value_loss)[:, None],
                                    np.asarray(per_it.valid)[:, None])
        med, sat, spread = (np.asarray(x) for x in inspect(state.params, task, jax.random.PRNGKey(1000 + i)))
        row = {"case": name, "family": family.name, "task": i + 1,
               "iterations": float(np.mean(metrics.iterations)),
               "iterations_per_seed": "/".join(str(int(x)) for x in np.asarray(metrics.iterations)),
               "solved": float(np.mean(metrics.solved)),
               "value_ev_mean": float(np.nanmean(fit.ev_mean)), "value_ev_last": float(np.nanmean(fit.ev_last)),
               "value_loss": float(np.nanmean(fit.value_loss)),
               "entropy_last": float(np.mean(networks.gaussian_entropy(state.params.policy["log_std"]))),
               **{f"median_pre{k + 1}": float(np.mean(med[:, k])) for k in range(med.shape[1])},
               **{f"saturated{k + 1}": float(np.mean(sat[:, k])) for k in range(sat.shape[1])},
               "v_std_over_ret_std": float(np.mean(spread)), "seconds": round(time.time() - t0, 1)}
        rows.append(row)
        print(" ".join(f"{k}={_fmt(v)}" for k, v in row.items()), flush=True)
    summary = {"case": name, "family": family.name, "task": "all", "sets": ",".join(f"{k}={v}" for k, v in
                                                                                        sets.items()) or "none"}
    for key in rows[0]:
        if key not in summary and isinstance(rows[0][key], float):
            summary[key] = float(np.mean([r[key] for r in rows]))
    print(" ".join(f"{k}={_fmt(v)}" for k, v in summary.items()), flush=True)
    return rows


def _fmt(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--family", default="point_goal", choices=envs.names())
    parser.add_argument("--tasks", type=int, default=3)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="a PPOConfig field for this case (repeatable), e.g. reward_scale=0.1")
    parser.add_argument("--case", default="default", help="the case's name in the output")
    args = parser.parse_args(argv)
    hostdevices.configure(1)
    run_case(envs.make(args.family), args, parse_sets(args.set), args.case)


if __name__ == "__main__":
    main()

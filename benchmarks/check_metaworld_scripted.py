"""Can the MetaWorld family's threshold be reached as jcomps measures it? MetaWorld's own scripted policies
(``metaworld.policies``) on the family's tasks, under our rules: T_max = 150 steps (MetaWorld's own step limit
off, as in the family), success rate = the fraction of episodes with at least one success step, threshold 0.2.

The family hides the goal from the observation (ML1's train tasks); a scripted policy needs it, so here the
policy is shown the environment's target in the observation's goal slot (``_partially_observable = False``
alone shows it at reset but not in the steps). The variants' resets are deterministic, so
episodes differ only by Gaussian action noise of std ``--noise`` (MetaWorld's own policy tests use 0.1); with 0
every episode is the same. One line per task as ``key=value`` pairs, then one per environment.

    python benchmarks/check_metaworld_scripted.py [--tasks P-0 B-1 H-2 ...] [--episodes 10] [--noise 0.1] \
        [--steps 150] [--reward v2|v1] [--trace K]

Default tasks: the first 9 of the paper's sequence (P-0 … H-8) and the held-out ones (P-39 … H-47).
"""

from __future__ import annotations

import argparse
import sys
import warnings

import numpy as np

from jcomps.envs import metaworld as family
from jcomps.envs import metaworld_host as host

POLICIES = {"P": "SawyerPushWallV3Policy", "B": "SawyerButtonPressWallV3Policy", "H": "SawyerHammerV3Policy"}


def parse_task(text: str) -> tuple[int, int]:
    """``P-3`` (or the code 3) -> (0, 3): the environment index and goal index of a task, read as ``--tasks``
    reads it (``MetaWorldFamily.parse_value``)."""
    mw = family.make()
    try:
        value = int(mw.parse_values([text])[0])
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return divmod(value, 100)


def episodes(env: int, goal: int, count: int, noise: float, seed: int, steps: int = host.MAX_STEPS,
             reward: str = "v2", trace: int = 0) -> np.ndarray:
    """Per episode: (any success step, first success step or -1, return) over ``steps`` steps. ``trace`` > 0
    prints the first episode's reward and MetaWorld's reward terms (its ``info``) every ``trace`` steps."""
    import metaworld.policies
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    policy = getattr(metaworld.policies, POLICIES[host.LETTERS[env]])()
    rng = np.random.default_rng(seed)
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        e = ALL_V3_ENVIRONMENTS[host.ENV_NAMES[env]](reward_function_version=reward)
        e.set_task(host.variants(env)[goal])
        e.max_path_length = np.iinfo(np.int32).max
        for _ in range(count):
            obs, _ = e.reset()
            first, total = -1, 0.0
            for t in range(steps):
                # The policy needs the goal, which the family's observations hide (the learners never see it):
                # the policy is shown the environment's target in the observation's goal slot.
                seen = np.array(obs, np.float64)
                seen[-3:] = e._target_pos
                action = policy.get_action(seen)
                action = np.clip(action + noise * rng.standard_normal(action.shape), -1.0, 1.0)
                obs, reward, _, _, info = e.step(action)
                total += float(reward)
                if trace and not out and t % trace == 0:
                    terms = " ".join(f"{k}={float(v):.3f}" for k, v in info.items() if k != "unscaled_reward")
                    print(f"trace task={host.LETTERS[env]}-{goal} step={t} reward={float(reward):.3f} {terms} "
                          f"hand={','.join(f'{x:.3f}' for x in obs[:3])} gripper={obs[3]:.3f} "
                          f"object={','.join(f'{x:.3f}' for x in obs[4:7])}", flush=True)
                if first < 0 and info["success"] > 0:
                    first = t
            out.append((first >= 0, first, total))
    return np.asarray(out, np.float64)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    default = [family.label(v) for v in family.SEQUENCE[:9] + family.HELD_OUT]
    parser.add_argument("--tasks", nargs="+", type=parse_task, default=[parse_task(t) for t in default])
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--noise", type=float, default=0.1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=host.MAX_STEPS,
                        help=f"episode length (default: the family's T_max, {host.MAX_STEPS}; MetaWorld's own is 500)")
    parser.add_argument("--trace", type=int, default=0, metavar="K",
                        help="print the first episode's reward and MetaWorld's reward terms every K steps")
    parser.add_argument("--reward", choices=host.REWARD_VERSIONS, default="v2",
                        help="MetaWorld's reward function (v2: the family metaworld; v1: metaworld_v1)")
    args = parser.parse_args()
    if args.episodes < 1 or args.steps < 1 or not args.noise >= 0 or args.trace < 0:
        sys.exit("--episodes and --steps must be >= 1, --noise and --trace >= 0")
    rates: dict = {}
    for env, goal in args.tasks:
        r = episodes(env, goal, args.episodes, args.noise, args.seed, args.steps, args.reward, args.trace)
        name = f"{host.LETTERS[env]}-{goal}"
        rate = float(r[:, 0].mean())
        rates.setdefault(host.LETTERS[env], []).append(rate)
        hit = r[r[:, 0] > 0, 1]
        print(f"task={name} reward={args.reward} episodes={args.episodes} steps={args.steps} noise={args.noise} "
              f"success_rate={rate:.2f} "
              f"reaches_threshold={rate >= family.SUCCESS_THRESHOLD} "
              f"first_success_step_median={float(np.median(hit)) if hit.size else -1:.0f} "
              f"mean_return={float(r[:, 2].mean()):.1f}", flush=True)
    for letter, values in rates.items():
        print(f"environment={letter} tasks={len(values)} mean_success_rate={np.mean(values):.2f} "
              f"tasks_at_threshold={sum(v >= family.SUCCESS_THRESHOLD for v in values)}", flush=True)


if __name__ == "__main__":
    main()

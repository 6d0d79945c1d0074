"""CoMPS on three Point Goal tasks, from Python: a family, a task sequence, a method, one jitted program."""
import dataclasses
import time

import jax

from jcomps import continual, envs, methods

family = envs.make("point_goal")                                   # or cheetah_vel, ant_goal, ant_dir, metaworld
tasks = envs.sequence(family, "non-stationary", num_tasks=3)       # a task pytree with a leading axis of 3
config = methods.default_config("comps", family)                   # the paper's defaults, calibrated per family
config = dataclasses.replace(config, max_tasks=3, ppo=dataclasses.replace(config.ppo, budget=100))
method = methods.make("comps", family, config)                     # a Method: pure init and learn_task

start = time.time()
state = method.init(jax.random.PRNGKey(0))
run = jax.jit(lambda state, tasks: continual.run_tasks(method, state, tasks))   # scan over tasks, one program
state, metrics = run(state, tasks)
for i, (its, solved) in enumerate(zip(metrics.iterations.tolist(), metrics.solved.tolist())):
    print(f"task {i + 1}: goal {float(tasks.goal[i, 0]):+.2f} {float(tasks.goal[i, 1]):+.2f}, "
          f"{'solved' if solved else 'not solved'} in {its} iterations")
print(f"{time.time() - start:.0f} s (compile included)")

"""The reinforcement-learning and meta-learning building blocks the methods are made of, pure functions under
``jit``/``vmap``: policy and value networks (``networks``), batched rollouts (``acting``), PPO's losses and update
(``ppo``), the RL step's iteration loop (``rl_loop``), V-trace (``vtrace``), the per-task experience stores
(``buffers``) and the meta step: a MAML-style outer update on stored experience (``meta``)."""

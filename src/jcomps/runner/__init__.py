"""The study runner: runs methods over a task sequence into a run directory, and nothing else.

``experiment`` is the host loop over chunks of tasks; ``programs`` compiles a method's learning and evaluation
programs; ``members`` lays the seeds (and a grid's points) over devices; ``grid`` turns hyperparameter grids into
vmapped axes; ``description`` is what defines a run (``RunDescription``, resolved once); ``rundir`` reads and writes
it as ``run.json`` and checks a resume against it; ``files`` writes JSON atomically (``RunError``); ``checkpoint``
and ``results`` write a run's state and raw metrics; ``events`` are the typed progress events the host loop hands
its one callback; ``distributed``, ``hostdevices`` and ``compile_cache`` set up processes, CPU devices and JAX's
persistent cache. Nothing here computes a statistic (``jcomps.analysis``)."""

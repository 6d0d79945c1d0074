"""The description of a run (``RunDescription``): everything that defines it, one typed object.

A run is its ``RunConfig`` (family, sequence, methods, seeds, tasks, chunking), its ``EvalConfig`` (resolved for
the family), every method's resolved config, the hyperparameter grid and the per-method ``--set`` overrides if any,
and the device and process counts (float rounding and each process's shards depend on them). ``resolve`` builds
it from the options a command line gave (the runner's script only parses them); ``to_json`` and ``from_json``
turn it into a run directory's ``run.json`` and back. ``from_json`` is the one place that reads what older
versions of jcomps wrote, by the tables of ``jcomps.migrations``: a field added since a run was made takes the value
the run had (its default, or ``EARLIER_VALUES``), a field it held as null because it followed another value (the
RL step's learning rate, the family's budget) takes that value, and either is listed in ``filled``; where the
addition changed what checkpoints hold (``UNRESUMABLE_BEFORE``, ``UNRESUMABLE_EVAL_BEFORE``, a ``format`` older than ``FORMAT``) the
description says why the run cannot be resumed (``unresumable``), and stays reportable.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Optional

import jax

from jcomps import configs, continual, envs, methods, migrations
from jcomps.numerics import check_field, check_finite_fields
from jcomps.runner import grid as grids
from jcomps.runner.files import RunError


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """What a run learns: the family, the sequence, the methods and the seeds."""

    family: str = "point_goal"
    """Task family (one of ``jcomps.envs.names()``)."""
    sequence: str = "non-stationary"
    """``non-stationary`` (the paper's order) or ``stationary`` (the same list shuffled by seed)."""
    methods: tuple[str, ...] = ("comps", "ppo_tl")
    """Methods to run, one compiled program each."""
    seeds: int = 4
    """Number of seeds (a vmap axis, sharded over devices)."""
    seed: int = 0
    """The first seed; seeds are seed, seed + 1, ..."""
    num_tasks: int = 6
    """Length of the sequence (a prefix of the family's list, shuffled per seed if stationary)."""
    tasks: tuple[str, ...] = ()
    """Chosen tasks, in the family's own terms, instead of the family's list (then ``num_tasks`` is their number):
    MetaWorld P-3, B-1, H-11 (or codes), goal velocities in m/s on Half-Cheetah, angles in degrees on Point Goal
    and the Ants. Every seed learns them in this order (``stationary``: shuffled by the seed)."""
    chunk_tasks: int = 2
    """Tasks per compiled chunk; a checkpoint is written after every chunk."""

    def __post_init__(self):
        check_finite_fields(self)
        check_field(self.family in envs.names(), "family", self.family, ", ".join(envs.names()))
        check_field(self.sequence in envs.SEQUENCE_KINDS, "sequence", self.sequence, ", ".join(envs.SEQUENCE_KINDS))
        check_field(len(self.methods) >= 1 and len(set(self.methods)) == len(self.methods), "methods", self.methods,
                    "one or more distinct method names")
        for name in self.methods:
            check_field(name in methods.names(), "methods", name, ", ".join(methods.names()))
        check_field(self.seeds >= 1, "seeds", self.seeds, "an integer >= 1")
        check_field(self.seed >= 0, "seed", self.seed, "an integer >= 0")
        check_field(self.num_tasks >= 1, "num_tasks", self.num_tasks, "an integer >= 1")
        if self.tasks:
            check_field(self.num_tasks == len(self.tasks), "num_tasks", self.num_tasks,
                        f"the number of tasks given ({len(self.tasks)}; the command line sets it when "
                        f"--num-tasks is left out)")
            canonical = canonical_tasks(self.family, self.tasks)
            check_field(self.tasks == canonical, "tasks", self.tasks,
                        f"the tasks by their canonical names ({', '.join(canonical)}: canonical_tasks)")
        check_field(self.chunk_tasks >= 1, "chunk_tasks", self.chunk_tasks, "an integer >= 1")

    @property
    def seed_list(self) -> list[int]:
        """The seeds, in order."""
        return list(range(self.seed, self.seed + self.seeds))


def canonical_tasks(family: str, tasks) -> tuple[str, ...]:
    """``tasks`` in ``family``'s terms by their canonical names, which a ``RunConfig`` holds, so that "10.0" and
    "10", or "102" and "B-2", are one run (resume, merge); ValueError naming ``tasks`` for one that is no task."""
    family = envs.make(family)
    try:
        family.parse_values(tasks)  # range-checked
        return tuple(family.task_name(family.parse_value(t)) for t in tasks)
    except ValueError as err:
        raise ValueError(f"tasks: {err}") from None


@dataclasses.dataclass(frozen=True)
class RunDescription:
    """Everything that defines a run (the module docstring); what ``run.json`` holds."""

    run: RunConfig
    eval: continual.EvalConfig
    """Resolved for the family (``EvalConfig.resolve``)."""
    methods: Mapping[str, Any]
    """Each method's resolved config, by name, in ``run.methods`` order."""
    grid: grids.Grid = ()
    """The hyperparameter grid's axes in ``--grid`` order; empty: no grid."""
    overrides: Mapping[str, Mapping[str, Any]] = dataclasses.field(default_factory=dict)
    """``--set`` per method ({method: {"field.path": value}}, values as JSON: lists for tuples), already part of
    ``methods``' configs."""
    devices: int = 1
    """Devices over every process."""
    processes: Optional[int] = 1
    """Processes the run is spread over (``jcomps.runner.distributed``); None in a merged study whose sources were
    spread differently (it is reported, never resumed)."""
    chunk_tasks_by_method: Optional[Mapping[str, int]] = None
    """A merged study's chunking per method where its sources chunked differently (``experiments/merge_runs.py``)."""
    format: int = migrations.FORMAT
    """What its checkpoints hold (``FORMAT``)."""
    filled: tuple[str, ...] = dataclasses.field(default=(), compare=False)
    """Fields its ``run.json`` lacked (made by an earlier version), filled with the values the run had."""
    unresumable: Optional[str] = dataclasses.field(default=None, compare=False)
    """Why this version cannot resume it (its checkpoints no longer fit), None when it can."""

    @property
    def family(self) -> envs.Family:
        return envs.make(self.run.family)

    def entries(self) -> list[tuple[str, str, Optional[dict]]]:
        """(method, results entry key, grid values or None) of every results entry: one per method without a
        grid, one per method and grid point with one."""
        if not self.grid:
            return [(m, m, None) for m in self.run.methods]
        out = []
        for m in self.run.methods:
            fields = {name for name, *_ in configs.flat_fields(type(self.methods[m]))}
            out += [(m, grids.key(m, values), dict(values)) for values in grids.point_values(fields, self.grid)]
        return out

    def config(self, method: str, values: Optional[dict] = None):
        """``method``'s config at grid point ``values`` (None: its config without a grid)."""
        config = self.methods[method]
        for field, value in (values or {}).items():
            config = grids.replace_flat(config, field, value)
        return config

    def programs(self, method: str) -> list:
        """``method``'s compiled programs (``jcomps.runner.grid.programs``)."""
        return grids.programs(method, self.methods[method], self.grid)

    def only(self, names) -> "RunDescription":
        """This description restricted to the methods in ``names``."""
        kept = tuple(m for m in self.run.methods if m in names)
        return dataclasses.replace(
            self, run=dataclasses.replace(self.run, methods=kept) if kept else self.run,
            methods={m: self.methods[m] for m in kept},
            overrides={m: v for m, v in self.overrides.items() if m in names},
            chunk_tasks_by_method=None if self.chunk_tasks_by_method is None else
            {m: c for m, c in self.chunk_tasks_by_method.items() if m in names})

    def to_json(self) -> dict:
        """``run.json``'s content."""
        run = configs.to_json(self.run)
        if self.chunk_tasks_by_method:
            run["chunk_tasks_by_method"] = dict(self.chunk_tasks_by_method)
        out = {"run": run, "eval": configs.to_json(self.eval),
               "methods": {name: configs.to_json(self.methods[name]) for name in self.run.methods},
               "devices": self.devices, "format": self.format}
        if self.processes is not None:
            out["processes"] = self.processes
        if self.grid:
            out["grid"] = grids.to_json(self.grid)
        if self.overrides:
            out["overrides"] = configs.to_json(self.overrides)
        return out


def _missing_leaves(stored: Mapping, default: Mapping, prefix: str = "") -> list[str]:
    """Dotted paths of the leaves of ``default`` (a config as JSON) that ``stored`` lacks."""
    out = []
    for key, value in default.items():
        if key not in stored:
            out.append(prefix + key)
        elif isinstance(value, dict) and isinstance(stored[key], dict):
            out += _missing_leaves(stored[key], value, f"{prefix}{key}.")
    return out


def _followed(stored: Mapping, resolved: Mapping, prefix: str = "") -> list[str]:
    """Dotted paths of the leaves that ``stored`` (a config as JSON) held as null and ``resolved`` fills: fields
    that followed another value, which runs made before the resolver recorded them left unfilled."""
    out = []
    for key, value in resolved.items():
        if isinstance(value, dict) and isinstance(stored.get(key), dict):
            out += _followed(stored[key], value, f"{prefix}{key}.")
        elif key in stored and stored[key] is None and value is not None:
            out.append(prefix + key)
    return out


def _section(data: Mapping, key: str, source: str) -> dict:
    value = data.get(key)
    if not isinstance(value, dict):
        raise RunError(f"{source}: '{key}' is missing or not an object; restore the file, or start the run anew in "
                       "another directory")
    return dict(value)


def from_json(data: Mapping, source: str = "run.json") -> RunDescription:
    """The description in ``run.json``'s content ``data`` (``source``: the file, for messages), read as every
    version of jcomps wrote it (the module docstring). RunError naming the file and the field where a value is
    missing or refused."""
    filled, unresumable = [], []

    def build(what: str, make):
        try:
            return make()
        except (ValueError, TypeError, KeyError) as err:
            raise RunError(f"{source}: {what}: {err}; restore the file, or start the run anew in another "
                           "directory") from None

    made = data.get("format", 1)
    if not isinstance(made, int) or made > migrations.FORMAT:
        raise RunError(f"{source}: format {made!r} is not one this version of jcomps reads (up to "
                       f"{migrations.FORMAT}); use the version that made it")
    if made < migrations.FORMAT:
        unresumable.append("; ".join(migrations.FORMAT_CHANGES[f] for f in range(made + 1, migrations.FORMAT + 1)))

    run_data = _section(data, "run", source)
    by_method = run_data.pop("chunk_tasks_by_method", None)
    filled += ["run." + k for k in _missing_leaves(run_data, configs.to_json(RunConfig()))]
    run = build("run", lambda: configs.config_from_dict(RunConfig(), run_data))

    eval_data = _section(data, "eval", source)
    for field in _missing_leaves(eval_data, configs.to_json(continual.EvalConfig())):
        filled.append("eval." + field)
        if field in migrations.UNRESUMABLE_EVAL_BEFORE:
            why = migrations.UNRESUMABLE_EVAL_BEFORE[field]
            unresumable.append(f"it was made before eval.{field} existed: {why}")
    eval_config = build("eval", lambda: configs.config_from_dict(continual.EvalConfig(), eval_data))
    if eval_config.heldout_budget is None:
        filled.append("eval.heldout_budget")  # made before the resolved value was recorded
        eval_config = eval_config.resolve(run.family)

    classes = {name: methods.config_class(name) for name in run.methods}
    grid = build("grid", lambda: grids.from_json(data.get("grid"), classes))
    grid_fields = frozenset(axis.field for axis in grid)
    stored_methods = _section(data, "methods", source)
    method_configs = {}
    for name in run.methods:
        stored = stored_methods.get(name)
        if not isinstance(stored, dict):
            raise RunError(f"{source}: methods.{name} is missing; restore the file, or start the run anew in another "
                           "directory")
        default = methods.default_config(name, run.family)
        for field in _missing_leaves(stored, configs.to_json(default)):
            filled.append(f"methods.{name}.{field}")
            if field in migrations.UNRESUMABLE_BEFORE:
                why = migrations.UNRESUMABLE_BEFORE[field]
                unresumable.append(f"it was made before methods.{name}.{field} existed: {why}")
        method_configs[name] = build(f"methods.{name}",
                                     lambda: methods.resolve_config(name, run.family, stored=stored,
                                                                    default=default, grid_fields=grid_fields))
        filled += [f"methods.{name}.{field}" for field in _followed(stored, configs.to_json(method_configs[name]))]
    overrides = data.get("overrides") or {}
    if not isinstance(overrides, dict):
        raise RunError(f"{source}: 'overrides' is not an object; restore the file")
    devices = data.get("devices")
    if not isinstance(devices, int) or isinstance(devices, bool) or devices < 1:
        raise RunError(f"{source}: devices is {devices!r}, not a device count; restore the file")
    if "processes" not in data:
        filled.append("processes")  # made before runs spread over processes
    return RunDescription(run=run, eval=eval_config, methods=method_configs, grid=grid, overrides=overrides,
                          devices=devices, processes=data.get("processes", 1), chunk_tasks_by_method=by_method,
                          format=made, filled=tuple(filled), unresumable="; ".join(unresumable) or None)


def resolve(options: Mapping[str, Any], *, set_specs=(), grid_specs=(),
            stored: Optional[RunDescription] = None) -> RunDescription:
    """The run a command line asks for, every layer resolved and validated once (ValueError naming the option).

    ``options``: {field: value} of the config options given (``--learning-rate``: the flat field names of
    ``RunConfig``, ``EvalConfig`` and the methods' configs, ``jcomps.configs.shared_options``); ``set_specs``:
    the ``--set METHOD.FIELD=VALUE`` words; ``grid_specs``: the ``--grid FIELD=VALUES`` words. With ``stored`` (a
    ``--resume``) the stored run is the base, options given again over it, and the stored grid and overrides
    unless given again; ``jcomps.runner.rundir.open_run_dir`` then refuses any difference. Each method's config
    comes from its layers (``jcomps.methods.resolve_config``, a resume's included: the recorded config is its
    layer): its registered default on the family, the shared options, one task slot per task, ``--set`` for that
    method alone, then the fields that follow another value filled (``jcomps.methods.with_followed``: ``run.json``
    records what runs, but for a field following a grid axis); a grid's points are built (and so checked) last.
    The device and process counts are JAX's.
    """
    options = dict(options)
    base = stored.run if stored else RunConfig()
    if options.get("tasks"):
        options["tasks"] = canonical_tasks(options.get("family") or base.family, options["tasks"])
        if options.get("num_tasks") is None:
            options["num_tasks"] = len(options["tasks"])  # --tasks without --num-tasks: as many as given
    run = configs.with_shared(base, options)
    eval_config = configs.with_shared(stored.eval if stored else continual.EvalConfig(), options).resolve(run.family)
    defaults = {name: methods.default_config(name, run.family) for name in run.methods}
    overrides = (configs.parse_overrides(set_specs, defaults) if set_specs or not stored
                 else {m: dict(v) for m, v in stored.overrides.items()})
    classes = {name: methods.config_class(name) for name in run.methods}
    grid = grids.parse(grid_specs, classes) if grid_specs else (stored.grid if stored is not None else ())
    grid_fields = frozenset(axis.field for axis in grid)
    method_configs = {}
    for name in run.methods:  # a resumed run's recorded config is its layer 3 (``methods.resolve_config``)
        recorded = stored.methods.get(name) if stored is not None else None
        method_configs[name] = methods.resolve_config(
            name, run.family, stored=None if recorded is None else configs.to_json(recorded), shared=options,
            num_tasks=run.num_tasks, overrides=overrides.get(name), default=defaults[name], grid_fields=grid_fields)
    for axis in grid:
        if options.get(axis.field) is not None:
            raise ValueError(f"--grid {axis.field}: also given as --{axis.field.replace('_', '-')}; give its values "
                             f"on the grid only")
        for method, values in overrides.items():
            if any(key.split(".")[-1] == axis.field for key in values):
                raise ValueError(f"--grid {axis.field}: also given by --set for {method}; give its values on the "
                                 f"grid only")
    family = envs.make(run.family)
    available = len(run.tasks or family.task_values)
    if run.num_tasks > available:
        raise ValueError(f"--num-tasks must be in [1, {available}] for {run.family}, got {run.num_tasks}")
    for name in run.methods:
        for point in grids.points(name, method_configs[name], grid):
            max_tasks = methods.task_slots(point.config)
            if max_tasks is not None and max_tasks < run.num_tasks:
                option = "--grid max_tasks=" if any(a.field == "max_tasks" for a in grid) else "--max-tasks "
                raise ValueError(f"{option}{max_tasks} is smaller than --num-tasks {run.num_tasks} ({name} keeps "
                                 f"one experience slot per task)")
    return RunDescription(run=run, eval=eval_config, methods=method_configs, grid=grid,
                          overrides=configs.to_json(overrides), devices=jax.device_count(),
                          processes=jax.process_count())


def describe(run: RunConfig, eval_config: continual.EvalConfig, method_configs: Mapping, grid: grids.Grid = (),
             overrides: Optional[Mapping] = None) -> RunDescription:
    """The description of a run made from configs already built (the library's way in, without a command line):
    ``eval_config`` resolved for the family, the fields of ``method_configs`` that follow another value filled
    (``jcomps.methods.with_followed``), JAX's device and process counts."""
    grid_fields = frozenset(axis.field for axis in grid)
    return RunDescription(run=run, eval=eval_config.resolve(run.family),
                          methods={name: methods.with_followed(method_configs[name], run.family, grid_fields)
                                   for name in run.methods}, grid=tuple(grid),
                          overrides=configs.to_json(overrides or {}), devices=jax.device_count(),
                          processes=jax.process_count())


def heldout_chosen(description: RunDescription) -> list[str]:
    """The chosen tasks (``RunConfig.tasks``) that the family holds out for its meta-test: a run that learns them
    has no unseen held-out tasks (the runner warns)."""
    family = description.family
    held = {family.task_name(v) for v in family.held_out_values}
    return [t for t in description.run.tasks if t in held]

"""Hyperparameter grids: an axis of a run, like the seeds.

``--grid learning_rate=0.01,0.001 --grid init_std=0.3,0.5`` runs every method of a run at every point of the
product of the values (in ``--grid`` order) × every seed. Grid fields are the flat option names of the method
configs (``jcomps.configs.flat_fields``; a name shared by nested configs, like ``discount`` in ``ppo`` and ``meta``,
sets all of them, as the plain option does). A method runs the axes it has; the others do not apply to it.

How a grid is compiled (``programs``): an axis whose field may hold a traced scalar in every config class of the
method that has it (the classes' ``TRACED``) and that has two or more values is a *traced* axis: its values are
an array over the members of one compiled program, and the method is made inside the traced function from a
config holding that member's tracer (``with_traced``). Every other axis (integers, tuples such as
``hidden_sizes``, booleans, fields not in ``TRACED``, and any axis with a single value, which is the same for
every member) is *static*: one program per combination of its values. Each program's members are its grid points
× the seeds, point-major (member ``p * seeds + s`` is point ``p``, seed ``s``).

A point's entry in ``results.json`` is ``METHOD[field=value,...]`` over the axes the method has, in ``--grid``
order (``key``); tuple values are written ``128x64``. A method that has none of the axes keeps its plain name.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import typing
from typing import Any, Optional

from jcomps import configs


@dataclasses.dataclass(frozen=True)
class Axis:
    """One ``--grid FIELD=V1,V2,...``: a flat config field and its parsed values."""

    field: str
    values: tuple


Grid = tuple  # tuple[Axis, ...], in --grid order


@dataclasses.dataclass(frozen=True)
class Point:
    """One grid point of one method: its entry name, the values of the axes it has, its concrete config."""

    method: str
    key: str
    values: tuple  # ((field, value), ...) in grid order
    config: Any


@dataclasses.dataclass(frozen=True)
class ProgramSpec:
    """One compiled program of a method: the points that share every static value.

    ``label`` names it in progress lines: the method name, or ``METHOD[field=value,...]`` over the static axes
    with several values; ``directory``, its checkpoint directory, is the same with ``@`` for the brackets
    (``ppo_tl@hidden_sizes=64x32``: Orbax cannot read back a checkpoint from a path with brackets).
    ``config`` is the concrete config of its first point; the ``traced`` fields are replaced, member by member,
    by that member's value (``with_traced``).
    """

    method: str
    label: str
    config: Any
    traced: tuple
    points: tuple

    @property
    def directory(self) -> str:
        return self.label if self.label == self.method else self.method + "@" + self.label[len(self.method) + 1:-1]


def _walk(cls, prefix=()):
    """(path, owner class, field name, type) of every leaf field of config dataclass ``cls``."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            yield from _walk(tp, prefix + (f.name,))
        else:
            yield prefix + (f.name,), cls, f.name, tp


def field_types(classes) -> dict:
    """Flat field name -> type over config classes ``classes`` (the first class that has it decides)."""
    out = {}
    for cls in classes:
        for name, tp, *_ in configs.flat_fields(cls):
            out.setdefault(name, tp)
    return out


def traced_fields(cls) -> frozenset:
    """Flat names of ``cls`` whose every occurrence (nested configs included) is in its class's ``TRACED``."""
    seen: dict = {}
    for _, owner, name, _ in _walk(cls):
        ok = name in getattr(owner, "TRACED", frozenset())
        seen[name] = seen.get(name, True) and ok
    return frozenset(n for n, ok in seen.items() if ok)


def format_value(value) -> str:
    """How a value is written in a key: ``0.001``, ``64``, ``128x64``, ``true``, ``none``."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "none"
    if isinstance(value, (tuple, list)):
        return "x".join(format_value(v) for v in value)
    return repr(value)


def key(method: str, values) -> str:
    """The results entry name of ``method`` at ``values`` ((field, value) pairs); the plain name without any."""
    values = list(values)
    if not values:
        return method
    return f"{method}[" + ",".join(f"{f}={format_value(v)}" for f, v in values) + "]"


def _parse_value(field: str, tp, text: str):
    if not text.strip():
        raise ValueError(f"--grid {field}: an empty value in the list")
    try:
        return configs.parse_value(tp, text)
    except ValueError as err:
        raise ValueError(f"--grid {field}: {err}") from None


def parse(specs, classes: dict) -> Grid:
    """The grid of ``--grid`` arguments ``specs`` (``FIELD=V1,V2,...``) for the method config classes ``classes``
    ({method name: class}). Raises ValueError naming the field for a malformed item, an unknown field (no class
    has it), an empty or repeated value, a field given twice. Values are checked against the configs by
    ``points``."""
    types = field_types(classes.values())
    axes = []
    for spec in specs or ():
        field, sep, rest = spec.partition("=")
        field = field.strip().replace("-", "_")
        if not sep or not field:
            raise ValueError(f"--grid {spec!r}: expected FIELD=VALUE,VALUE,...")
        if field not in types:
            raise ValueError(f"--grid {field}: unknown field; no method in --methods ({', '.join(classes)}) has it")
        if any(a.field == field for a in axes):
            raise ValueError(f"--grid {field}: given twice; give all its values in one --grid {field}=V1,V2,...")
        if not rest.strip():
            raise ValueError(f"--grid {field}: empty list of values")
        values = tuple(_parse_value(field, types[field], t) for t in rest.split(","))
        for i, v in enumerate(values):
            if v in values[:i]:
                raise ValueError(f"--grid {field}: value {format_value(v)} given twice")
        axes.append(Axis(field, values))
    return tuple(axes)


def to_json(grid: Grid) -> list:
    """``[[field, [values...]], ...]`` (a list, so that a resume also checks the order)."""
    return [[a.field, [list(v) if isinstance(v, tuple) else v for v in a.values]] for a in grid]


def from_json(data, classes: dict) -> Grid:
    """The inverse of ``to_json`` (lists of tuple-typed fields become tuples again)."""
    types = field_types(classes.values())
    axes = []
    for field, values in data or ():
        tuple_typed = typing.get_origin(types.get(field)) is tuple
        axes.append(Axis(field, tuple(tuple(v) if tuple_typed and isinstance(v, list) else v for v in values)))
    return tuple(axes)


def replace_flat(config, field: str, value):
    """``config`` with every occurrence of flat field ``field`` set to ``value``, validated (the config classes'
    own checks run: a refused value raises their ValueError)."""
    changes = {}
    for f in dataclasses.fields(config):
        current = getattr(config, f.name)
        if dataclasses.is_dataclass(current):
            changes[f.name] = replace_flat(current, field, value)
        elif f.name == field:
            changes[f.name] = value
    return dataclasses.replace(config, **changes)


def with_traced(config, values: dict):
    """``config`` with its traced fields named in ``values`` set to those values (a member's hyperparameters, the
    arguments of a compiled program: tracers), every nested occurrence included. A config holding a tracer skips
    its checks (``jcomps.numerics.holds_tracers``): every concrete value is checked beforehand (``points``)."""
    traced = getattr(type(config), "TRACED", frozenset())
    changes = {}
    for f in dataclasses.fields(config):
        current = getattr(config, f.name)
        if dataclasses.is_dataclass(current):
            changes[f.name] = with_traced(current, values)
        elif f.name in values and f.name in traced:
            changes[f.name] = values[f.name]
    return dataclasses.replace(config, **changes)


def axes_of(method_fields, grid: Grid) -> list:
    """The axes of ``grid`` whose field is in ``method_fields``, in grid order."""
    return [a for a in grid if a.field in method_fields]


def point_values(method_fields, grid: Grid) -> list:
    """Every point of ``grid`` for a method with fields ``method_fields``: (field, value) tuples, product order."""
    axes = axes_of(method_fields, grid)
    return [tuple(zip([a.field for a in axes], combo)) for combo in itertools.product(*[a.values for a in axes])]


def points(method: str, base, grid: Grid) -> list:
    """The grid points of ``method`` with base config ``base``; every concrete config is built (and so checked).

    Raises ValueError naming the field and value the config refuses.
    """
    fields = {name for name, *_ in configs.flat_fields(type(base))}
    for axis in axes_of(fields, grid):  # one value at a time first, so the error names it
        for v in axis.values:
            try:
                replace_flat(base, axis.field, v)
            except (ValueError, TypeError) as err:
                raise ValueError(f"--grid {axis.field}={format_value(v)}: {err}") from None
    out = []
    for values in point_values(fields, grid):
        config = base
        for field, v in values:
            try:
                config = replace_flat(config, field, v)
            except (ValueError, TypeError) as err:
                raise ValueError(f"--grid point {key(method, values)}: {err}") from None
        out.append(Point(method, key(method, values), values, config))
    return out


def programs(method: str, base, grid: Grid) -> list:
    """The compiled programs of ``method`` (see the module docstring), each with its points in product order."""
    fields = {name for name, *_ in configs.flat_fields(type(base))}
    axes = axes_of(fields, grid)
    traceable = traced_fields(type(base))
    traced = tuple(a.field for a in axes if a.field in traceable and len(a.values) > 1)
    labelled = [a.field for a in axes if a.field not in traced and len(a.values) > 1]
    groups: dict = {}
    for p in points(method, base, grid):
        static = tuple((f, v) for f, v in p.values if f not in traced)
        groups.setdefault(static, []).append(p)
    out = []
    for static, pts in groups.items():
        label = key(method, [(f, v) for f, v in static if f in labelled])
        out.append(ProgramSpec(method, label, pts[0].config, traced, tuple(pts)))
    return out


def best(entries_: list, iterations: dict, returns: dict) -> dict:
    """{method: key} of each method's best entry: the lowest mean iterations-to-success, ties broken by the
    higher mean return (``iterations`` and ``returns``: {key: mean}); NaN counts as worst."""
    out: dict = {}
    rank = lambda k: (_finite_or(iterations[k], math.inf), -_finite_or(returns[k], -math.inf))  # noqa: E731
    for method, k, _ in entries_:
        if method not in out or rank(k) < rank(out[method]):
            out[method] = k
    return out


def _finite_or(x: Optional[float], default: float) -> float:
    return default if x is None or not math.isfinite(x) else float(x)

"""Command-line options derived from the config dataclasses, so that no option is written twice.

Every field of a config dataclass becomes ``--field-name`` (nested config dataclasses are flattened: the
fields of ``PPOTLConfig.ppo`` become top-level options). Methods that share a field name (all of them share
the PPO fields) share the option. The field's docstring, the attribute docstring under it, is its help text.

``--set METHOD.FIELD[.FIELD]=VALUE`` (``parse_overrides``, ``apply_overrides``) changes one method alone, by the
field's full path (``--set gmps_ppo_is.meta.inner_learning_rate=0.01``); it wins over the shared options.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import math
import re
import typing
from typing import Optional


def _field_docs(cls) -> dict[str, str]:
    """Attribute docstrings (the string literal right after a field) of a dataclass."""
    try:
        tree = ast.parse(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    docs, body = {}, tree.body[0].body
    for node, nxt in zip(body, body[1:]):
        if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str)):
            docs[node.target.id] = nxt.value.value.strip()
    return docs


def flat_fields(cls) -> list[tuple[str, type, object, str]]:
    """(name, type, default, help) of every leaf field of dataclass ``cls``, nested configs flattened."""
    hints = typing.get_type_hints(cls)
    docs = _field_docs(cls)
    out = []
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            out.extend(flat_fields(tp))
        else:
            out.append((f.name, tp, f.default, docs.get(f.name, "")))
    return out


def _parse_int(s: str) -> int:
    try:
        return int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None


def _parse_float(s: str) -> float:
    try:
        value = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {s!r}")
    return value


def _parser_for(tp):
    """The function that parses one command-line word as a value of field type ``tp``; it raises
    ``argparse.ArgumentTypeError`` naming the expected type (argparse then names the option)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Union and type(None) in args:
        inner = _parser_for(next(a for a in args if a is not type(None)))

        def parse_optional(s):
            if s.lower() == "none":
                return None
            try:
                return inner(s)
            except argparse.ArgumentTypeError as err:
                expected = str(err).split(", got ")[0]
                raise argparse.ArgumentTypeError(f"{expected} or none, got {s!r}") from None
        return parse_optional
    if tp is bool:
        def parse_bool(s):
            if s.lower() in ("1", "true", "yes", "on"):
                return True
            if s.lower() in ("0", "false", "no", "off"):
                return False
            raise argparse.ArgumentTypeError(f"expected true or false, got {s!r}")
        return parse_bool
    if origin is tuple:
        return _parser_for(args[0])  # one element per command-line word (nargs="+"), made a tuple by shared_options
    return {int: _parse_int, float: _parse_float}.get(tp, tp)


def add_config_args(parser: argparse.ArgumentParser, classes, family_values: Optional[dict] = None,
                    method_values: Optional[dict] = None) -> None:
    """Adds one ``--option`` per distinct leaf field of the config dataclasses ``classes`` (default: unset).

    The help shows, after a field's default, ``family_values`` ({field: {family: value}},
    ``jcomps.envs.settings_by_field()``) where a family's calibrated setting differs from the default, then
    ``method_values`` ({field: {"family (method.part)": value}}, ``jcomps.methods.settings_by_field()``): a method's
    own calibration on a family, always shown (it replaces the family's value, whatever the default)."""
    seen = {o for a in parser._actions for o in a.option_strings}
    family_values, method_values = family_values or {}, method_values or {}
    show = lambda v: " ".join(map(str, v)) if isinstance(v, tuple) else str(v)  # noqa: E731
    for cls in classes:
        group = parser.add_argument_group(f"{cls.__name__} options")
        for name, tp, default, doc in flat_fields(cls):
            flag = "--" + name.replace("_", "-")
            if flag in seen:
                continue
            seen.add(flag)
            by_value: dict = {}
            for family, value in family_values.get(name, {}).items():
                if value != default:
                    by_value.setdefault(show(value), []).append(family)
            for label, value in method_values.get(name, {}).items():
                by_value.setdefault(show(value), []).append(label)
            shown = show(default) + "".join(f"; {', '.join(labels)}: {v}" for v, labels in by_value.items())
            nargs = "+" if typing.get_origin(tp) is tuple else None
            group.add_argument(flag, dest=f"cfg_{name}", type=_parser_for(tp), nargs=nargs, default=None,
                               metavar=name.upper(), help=f"{doc} (default: {shown})".replace("%", "%%"))


def shared_options(args: Optional[argparse.Namespace]) -> dict:
    """{field: value} of the config options given on the command line (lists made tuples)."""
    if args is None:
        return {}
    return {key[len("cfg_"):]: tuple(value) if isinstance(value, list) else value
            for key, value in vars(args).items() if key.startswith("cfg_") and value is not None}


def with_shared(config, shared: dict):
    """``config`` with every leaf field named in ``shared`` ({field: value}) set, every nested occurrence."""
    changes = {}
    for f in dataclasses.fields(config):
        current = getattr(config, f.name)
        if dataclasses.is_dataclass(current):
            changes[f.name] = with_shared(current, shared)
        elif f.name in shared:
            changes[f.name] = shared[f.name]
    return dataclasses.replace(config, **changes)


def to_json(x):
    """A config dataclass (or a tuple or mapping of them, or a value) as JSON data: dicts of fields, lists for
    tuples; ``config_from_dict`` reads it back."""
    if dataclasses.is_dataclass(x):
        return {f.name: to_json(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, (tuple, list)):
        return [to_json(v) for v in x]
    if isinstance(x, dict):
        return {k: to_json(v) for k, v in x.items()}
    return x


def config_from_dict(base, data: dict):
    """``base`` (a config instance: the method's registered default on the run's family) with the values of its
    ``dataclasses.asdict``-like ``data`` (lists become tuples; fields missing from ``data`` keep ``base``'s value)."""
    changes = {}
    for f in dataclasses.fields(base):
        current = getattr(base, f.name)
        if dataclasses.is_dataclass(current):
            changes[f.name] = config_from_dict(current, data.get(f.name) or {})
        elif f.name in data:
            value = data[f.name]
            changes[f.name] = tuple(value) if isinstance(value, list) else value
    return dataclasses.replace(base, **changes)


def parse_value(tp, text: str):
    """A command-line word as a value of field type ``tp`` (tuples: ``128x64`` or ``128,64``; optionals: ``none``).
    Raises ValueError."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    text = text.strip()
    try:
        if origin is tuple:
            return tuple(_parser_for(args[0])(x) for x in re.split(r"[x,\s]+", text))
        return _parser_for(tp)(text)
    except (ValueError, TypeError, argparse.ArgumentTypeError) as err:
        raise ValueError(f"cannot parse {text!r} as {getattr(tp, '__name__', tp)} ({err})") from None


def _leaf_type(config, path: list[str], where: str):
    """The type of the leaf field at ``path`` of ``config``; ValueError naming what is allowed."""
    hints = typing.get_type_hints(type(config))
    names = [f.name for f in dataclasses.fields(config)]
    head = path[0]
    if head not in names:
        raise ValueError(f"{where}: unknown field {head!r}; allowed: {', '.join(names)}")
    current = getattr(config, head)
    if dataclasses.is_dataclass(current):
        if len(path) == 1:
            inner = [f.name for f in dataclasses.fields(current)]
            raise ValueError(f"{where}: {head} is a group of fields; name one: {head}.{{{','.join(inner)}}}")
        return _leaf_type(current, path[1:], where)
    if len(path) > 1:
        raise ValueError(f"{where}: {head} is a field, not a group ({'.'.join(path[1:])} cannot follow it)")
    return hints[head]


def set_path(config, path, value):
    """``config`` with the leaf at dotted ``path`` (a tuple of names) set to ``value``, validated by the config
    classes' own checks."""
    head, rest = path[0], path[1:]
    if rest:
        return dataclasses.replace(config, **{head: set_path(getattr(config, head), rest, value)})
    return dataclasses.replace(config, **{head: value})


def parse_overrides(specs, configs: dict) -> dict:
    """``--set METHOD.FIELD[.FIELD]=VALUE`` arguments as {method: {"field.path": value}}, each checked against
    ``configs`` ({method: its config}): the method must be one of the run's, the path a leaf field, the value of
    its type. Raises ValueError naming the argument and what is allowed."""
    out: dict = {}
    for spec in specs or ():
        target, sep, text = spec.partition("=")
        parts = [p.strip().replace("-", "_") for p in target.split(".")]
        if not sep or len(parts) < 2 or not all(parts):
            raise ValueError(f"--set {spec!r}: expected METHOD.FIELD[.FIELD]=VALUE, e.g. "
                             "comps.meta.inner_learning_rate=0.01")
        method, path = parts[0], parts[1:]
        where = f"--set {target.strip()}"
        if method not in configs:
            raise ValueError(f"{where}: method {method!r} is not in this run; its methods: {', '.join(configs)}")
        tp = _leaf_type(configs[method], path, where)
        try:
            value = parse_value(tp, text)
        except ValueError as err:
            raise ValueError(f"{where}: {err}") from None
        key = ".".join(path)
        if key in out.get(method, {}):
            raise ValueError(f"{where}: given twice")
        out.setdefault(method, {})[key] = value
    return out


def apply_overrides(configs: dict, overrides: dict) -> dict:
    """``configs`` with each method's ``overrides`` ({"field.path": value}) set; a refused value raises a
    ValueError naming ``--set METHOD.PATH``."""
    out = dict(configs)
    for method, values in overrides.items():
        for key, value in values.items():
            value = tuple(value) if isinstance(value, list) else value
            try:
                out[method] = set_path(out[method], tuple(key.split(".")), value)
            except ValueError as err:
                raise ValueError(f"--set {method}.{key}: {err}") from None
    return out

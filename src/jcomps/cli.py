"""Command-line options derived from the config dataclasses, so that no option is written twice.

Every field of a config dataclass becomes ``--field-name`` (nested config dataclasses are flattened: the
fields of ``PPOTLConfig.ppo`` become top-level options). Methods that share a field name (all of them share
the PPO fields) share the option. The field's docstring, the attribute docstring under it, is its help text.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
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


def _parser_for(tp):
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Union and type(None) in args:
        inner = _parser_for(next(a for a in args if a is not type(None)))
        return lambda s: None if s.lower() == "none" else inner(s)
    if tp is bool:
        def parse_bool(s):
            if s.lower() in ("1", "true", "yes", "on"):
                return True
            if s.lower() in ("0", "false", "no", "off"):
                return False
            raise argparse.ArgumentTypeError(f"expected true or false, got {s!r}")
        return parse_bool
    if origin is tuple:
        return args[0]  # one element per command-line word (nargs="+"), made a tuple by build_config
    return tp


def add_config_args(parser: argparse.ArgumentParser, classes) -> None:
    """Adds one ``--option`` per distinct leaf field of the config dataclasses ``classes`` (default: unset)."""
    seen = {o for a in parser._actions for o in a.option_strings}
    for cls in classes:
        group = parser.add_argument_group(f"{cls.__name__} options")
        for name, tp, default, doc in flat_fields(cls):
            flag = "--" + name.replace("_", "-")
            if flag in seen:
                continue
            seen.add(flag)
            shown = " ".join(map(str, default)) if isinstance(default, tuple) else default
            nargs = "+" if typing.get_origin(tp) is tuple else None
            group.add_argument(flag, dest=f"cfg_{name}", type=_parser_for(tp), nargs=nargs, default=None,
                               metavar=name.upper(), help=f"{doc} (default: {shown})")


def build_config(cls, args: argparse.Namespace, base=None):
    """An instance of config dataclass ``cls`` with the options given on the command line, and elsewhere the
    values of ``base`` (an instance of ``cls``, e.g. a family's defaults) or, without it, the class defaults."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        inner = None if base is None else getattr(base, f.name)
        if dataclasses.is_dataclass(hints[f.name]):
            kwargs[f.name] = build_config(type(inner) if inner is not None else hints[f.name], args, inner)
        else:
            value = getattr(args, f"cfg_{f.name}", None)
            if value is not None:
                kwargs[f.name] = tuple(value) if isinstance(value, list) else value
            elif base is not None:
                kwargs[f.name] = inner
    return cls(**kwargs)


def config_from_dict(cls, data: dict, args: Optional[argparse.Namespace] = None):
    """An instance of ``cls`` from its ``dataclasses.asdict``-like ``data`` (lists become tuples), with any
    options given on the command line in ``args`` put over it."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            kwargs[f.name] = config_from_dict(hints[f.name], data.get(f.name, {}), args)
            continue
        value = data.get(f.name, f.default)
        given = getattr(args, f"cfg_{f.name}", None) if args is not None else None
        if given is not None:
            value = given
        kwargs[f.name] = tuple(value) if isinstance(value, list) else value
    return cls(**kwargs)

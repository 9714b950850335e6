"""Command-line flags made from dataclass fields, so a setting is declared once: in its config.

A field whose metadata is :func:`flag` gets one argparse option, with the field's default and
type; a field whose metadata is :func:`nested` lends the flags of its own dataclass's fields.
:func:`add_flags` adds the options, :func:`config_from_flags` builds the config
back from the parsed namespace. :func:`real_number` and :func:`whole_number` are the checks the
configs' ``__post_init__`` apply to their fields.

Example:
    >>> import argparse
    >>> from dataclasses import dataclass, field
    >>> @dataclass
    ... class Run:
    ...     steps: int = field(default=10, metadata=flag("optimiser steps"))
    ...     warmup_steps: int = field(default=2, metadata=flag("warm-up steps", flag="--warmup"))
    ...     note: str = "no flag"
    >>> parser = argparse.ArgumentParser()
    >>> add_flags(parser, Run)
    >>> config_from_flags(parser.parse_args(["--warmup", "5"]), Run)
    Run(steps=10, warmup_steps=5, note='no flag')
    >>> parser._option_string_actions["--steps"].help
    'optimiser steps (default: 10)'
"""

from __future__ import annotations

import argparse
import math
import numbers
from collections.abc import Iterator
from dataclasses import MISSING, Field, fields


def flag(help: str, **argparse_options) -> dict:
    """A field's metadata giving it a command-line flag: ``help`` and argparse options.

    The flag is ``--<field-name>`` (``-`` for ``_``) unless ``flag="--other"`` is given; its
    destination is the field's name; its default and type are the field's, unless the options
    give ``default``, ``type`` or ``required``. ``shown="text"`` states the default in the help
    instead of the value (e.g. "all" for None); a flag with an ``action`` states its own."""
    return {"cli": {"help": help, **argparse_options}}


def nested() -> dict:
    """A field's metadata: the flags of its dataclass's fields (built by its default factory)
    are flags of the command too, with their own names as destinations."""
    return {"cli_nested": True}


def field_default(f: Field):
    """The field's default value (a fresh one from its factory), or ``dataclasses.MISSING``."""
    if f.default is not MISSING:
        return f.default
    return f.default_factory() if f.default_factory is not MISSING else MISSING


def flag_fields(cls) -> Iterator[Field]:
    """The fields of dataclass ``cls`` that have a flag, nested configs' fields in their place."""
    for f in fields(cls):
        if f.metadata.get("cli_nested"):
            yield from flag_fields(type(field_default(f)))
        elif "cli" in f.metadata:
            yield f


def flag_options(f: Field) -> tuple[str, dict]:
    """The flag of field ``f`` (:func:`flag`) and the argparse options it is added with."""
    options = dict(f.metadata["cli"])
    name = options.pop("flag", "--" + f.name.replace("_", "-"))
    shown = options.pop("shown", None)
    value = field_default(f)
    default = options.pop("default", value)
    if default is MISSING:
        options.setdefault("required", True)
    if options.get("required"):
        default = None
    if options.get("action") is None:
        options.setdefault("type", str if value is None or value is MISSING else type(value))
        if not options.get("required"):
            if shown is None:
                shown = "all" if default is None and options.get("nargs") else default
                shown = " ".join(map(str, shown)) if isinstance(shown, tuple) else shown  # as typed: --flag 1 1
            options["help"] += f" (default: {shown})"
    return name, {"dest": f.name, "default": default, **options}


def add_flags(parser: argparse.ArgumentParser, cls, only: tuple[str, ...] | None = None) -> None:
    """Add a flag for every field of dataclass ``cls`` that has one (:func:`flag`), nested
    configs' included, or for the fields named in ``only`` (a command that takes some of a
    config's settings): the command line and the config cannot drift apart."""
    dests = [f.name for f in flag_fields(cls)]
    twice = sorted({d for d in dests if dests.count(d) > 1})
    if twice:
        raise ValueError(f"{cls.__name__}: fields {twice} would share a flag's destination")
    unknown = sorted(set(only or ()) - set(dests))
    if unknown:
        raise ValueError(f"{cls.__name__}: no field with a flag named {unknown}")
    for f in flag_fields(cls):
        if only is not None and f.name not in only:
            continue
        name, options = flag_options(f)
        parser.add_argument(name, **options)


def config_from_flags(args: argparse.Namespace, cls, **fixed):
    """The ``cls`` of the flags :func:`add_flags` added, parsed into ``args``, and the
    ``fixed`` fields (given values win; a nested config not given is built from its flags)."""
    values = {}
    for f in fields(cls):
        if f.name in fixed:
            continue
        if f.metadata.get("cli_nested"):
            values[f.name] = config_from_flags(args, type(field_default(f)))
        elif "cli" in f.metadata:
            values[f.name] = getattr(args, f.name)
    return cls(**values, **fixed)


def real_number(value) -> bool:
    """A finite real number, NumPy's included (not a bool)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def whole_number(value) -> bool:
    """An integer, NumPy's included (not a bool)."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)

"""Option tables for the docs made from a config dataclass, so a setting is described once: in
its class docstring's ``Attributes:`` section, beside its field and its flag.

:func:`options_table` gives a Markdown table with one row per ``Attributes:`` entry (an entry
may name several fields, ``a, b: text``): the fields, their defaults, their command-line flags
(:mod:`.config_flags`) and the entry's text. A field without an entry, or an entry naming no
field, is an error, so the docstring cannot fall behind the fields. ``scripts/docs_tables.py``
writes the tables into the docs.

Example:
    >>> from dataclasses import dataclass, field
    >>> from gensplat_transforms.core.config_flags import flag
    >>> @dataclass
    ... class Run:
    ...     '''Attributes:
    ...         steps: optimiser steps (``--steps``).
    ...         lr, warmup: peak learning rate and
    ...             its warm-up length.
    ...     '''
    ...     steps: int = field(default=10, metadata=flag("optimiser steps"))
    ...     lr: float = 1e-3
    ...     warmup: int = 2
    >>> print(options_table(Run))
    | field | default | flag | meaning |
    |---|---|---|---|
    | `steps` | 10 | `--steps` | optimiser steps (`--steps`). |
    | `lr`, `warmup` | 0.001, 2 |  | peak learning rate and its warm-up length. |
"""

from __future__ import annotations

import dataclasses
import inspect
import re

from .config_flags import field_default, flag_options

_ENTRY = re.compile(r"^(\w+(?:,\s*\w+)*):\s*(.*)$")
_ROLE = re.compile(r":(?:func|mod|class|meth|data|attr):`[~.]*([^`]+)`")


def field_docs(cls) -> list[tuple[tuple[str, ...], str]]:
    """The ``Attributes:`` entries of dataclass ``cls``'s docstring, in order: (the field names
    an entry gives, its text on one line). Raises ValueError naming a field without an entry
    or an entry that is not a field."""
    lines = inspect.cleandoc(cls.__doc__ or "").splitlines()
    try:
        start = next(i for i, line in enumerate(lines) if line.strip() == "Attributes:")
    except StopIteration:
        raise ValueError(f"{cls.__name__}: its docstring has no 'Attributes:' section") from None
    entries: list[tuple[tuple[str, ...], list[str]]] = []
    indent = None
    for line in lines[start + 1:]:
        if not line.strip():
            if entries:
                break
            continue
        depth = len(line) - len(line.lstrip())
        indent = depth if indent is None else indent
        if depth < indent:
            break
        match = _ENTRY.match(line.strip()) if depth == indent else None
        if match:
            entries.append((tuple(n.strip() for n in match[1].split(",")), [match[2]]))
        elif entries:
            entries[-1][1].append(line.strip())
    documented = [(names, " ".join(text)) for names, text in entries]
    named = [n for names, _ in documented for n in names]
    fields = [f.name for f in dataclasses.fields(cls)]
    missing = [f for f in fields if f not in named]
    unknown = [n for n in named if n not in fields]
    if missing or unknown:
        raise ValueError(f"{cls.__name__}'s docstring: fields without an 'Attributes:' entry {missing}, "
                         f"entries naming no field {unknown}")  # fmt: skip
    return documented


def options_table(cls) -> str:
    """A Markdown table of dataclass ``cls``'s settings: field, default, flag, meaning
    (:func:`field_docs`); docstring markup (````x````, ``:func:`x```) becomes Markdown code."""
    by_name = {f.name: f for f in dataclasses.fields(cls)}
    rows = ["| field | default | flag | meaning |", "|---|---|---|---|"]
    for names, text in field_docs(cls):
        found = [by_name[n] for n in names]
        defaults = ", ".join(_default(f) for f in found)
        flags = ", ".join(f"`{flag_options(f)[0]}`" for f in found if "cli" in f.metadata)
        meaning = _ROLE.sub(r"`\1`", text).replace("``", "`").replace("|", "\\|")
        rows.append(f"| {', '.join(f'`{n}`' for n in names)} | {defaults} | {flags} | {meaning} |")
    return "\n".join(rows)


def _default(f: dataclasses.Field) -> str:
    value = field_default(f)
    if value is dataclasses.MISSING:
        return "required"
    if dataclasses.is_dataclass(value):
        return f"`{type(value).__name__}()`"
    if value is None or isinstance(value, (bool, int, float)):
        return str(value)
    return f"`{value!r}`"

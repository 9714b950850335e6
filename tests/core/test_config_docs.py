"""Option tables from a config's docstring: entries, groups, continuation lines, and refusals."""

from dataclasses import dataclass, field

import pytest

from gensplat_transforms.core.config_docs import field_docs, options_table
from gensplat_transforms.core.config_flags import flag, nested


@dataclass
class Inner:
    """Attributes:
    depth: a weight.
    """

    depth: float = field(default=0.1, metadata=flag("weight", flag="--l-depth"))


@dataclass
class Run:
    """Settings of a run.

    Attributes:
        name: the run's name; a ``str`` (:func:`.core.atomic.atomic_write`).
        steps, batch: optimiser steps and
            samples per step | a pipe.
        inner: nested settings.

    Example:
        >>> Run().steps
        3
    """

    name: str = "run"
    steps: int = field(default=3, metadata=flag("steps"))
    batch: int = field(default=2, metadata=flag("batch", flag="--bs"))
    inner: Inner = field(default_factory=Inner, metadata=nested())


def test_entries_groups_and_continuations_are_read_up_to_the_next_section():
    assert field_docs(Run) == [(("name",), "the run's name; a ``str`` (:func:`.core.atomic.atomic_write`)."),
                               (("steps", "batch"), "optimiser steps and samples per step | a pipe."),
                               (("inner",), "nested settings.")]  # fmt: skip


def test_the_table_has_defaults_flags_and_markdown_code():
    rows = options_table(Run).splitlines()
    assert rows[0] == "| field | default | flag | meaning |"
    assert rows[2] == "| `name` | `'run'` |  | the run's name; a `str` (`core.atomic.atomic_write`). |"
    assert rows[3] == "| `steps`, `batch` | 3, 2 | `--steps`, `--bs` | optimiser steps and samples per step \\| a pipe. |"
    assert rows[4] == "| `inner` | `Inner()` |  | nested settings. |"
    assert "`--l-depth`" in options_table(Inner)


def test_a_field_without_an_entry_or_an_entry_without_a_field_is_refused():
    @dataclass
    class Missing:
        """Attributes:
        a: documented.
        ghost: no such field.
        """

        a: int = 1
        b: int = 2

    with pytest.raises(ValueError, match=r"without an 'Attributes:' entry \['b'\].*naming no field \['ghost'\]"):
        field_docs(Missing)

    @dataclass
    class Bare:
        x: int = 1

    Bare.__doc__ = "No sections."
    with pytest.raises(ValueError, match="no 'Attributes:' section"):
        options_table(Bare)

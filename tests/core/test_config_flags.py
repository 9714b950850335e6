"""config_flags: a command may take some of a config's flags (``only``), never a name it lacks."""

import argparse
from dataclasses import dataclass, field

import pytest

from gensplat_transforms.core.config_flags import add_flags, flag


@dataclass
class Run:
    steps: int = field(default=10, metadata=flag("optimiser steps"))
    lr: float = field(default=1e-3, metadata=flag("learning rate"))
    note: str = "no flag"


def test_only_adds_the_named_fields_flags():
    parser = argparse.ArgumentParser()
    add_flags(parser, Run, only=("lr",))
    assert vars(parser.parse_args(["--lr", "0.5"])) == {"lr": 0.5}
    with pytest.raises(SystemExit):
        parser.parse_args(["--steps", "3"])


def test_only_refuses_a_field_without_a_flag():
    with pytest.raises(ValueError, match=r"Run: no field with a flag named \['note', 'step'\]"):
        add_flags(argparse.ArgumentParser(), Run, only=("step", "note"))

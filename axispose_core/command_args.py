"""What the command modules share: the `add_parser` each command is added with, and the argument types several
commands take. It imports nothing of the core, so every command module (and `axispose_ros.cli`) can use it.

A command module imports what its bodies run inside them: every call builds the whole parser, which stays light."""

from __future__ import annotations

import argparse
from collections.abc import Callable

AddParser = Callable[..., argparse.ArgumentParser]
"""`add_parser` of the subcommands: what a command's adder (and `cli.build_parser`'s `commands`) adds commands with."""
Command = Callable[[AddParser], None]
"""A command's adder: declares its options and sets its body as `func`."""


def object_ids(text: str) -> list[int]:
    """The argparse type of `--objects`: comma-separated object ids (the ROS commands' too)."""
    return [int(v) for v in text.split(",") if v.strip()]

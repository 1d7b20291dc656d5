"""argparse value types shared by every command line: each error names the flag and the rule.

Torch-free and mujoco-free, like the rest of :mod:`firp.core`: the sim worker's, the planner's and
the service's command lines use them as well as training's.
"""

from __future__ import annotations

import argparse
from typing import Callable


def _checked(name: str, cast: Callable[[str], float], kind: str, ok: Callable[[float], bool],
             rule: str) -> Callable[[str], float]:
    """A parser that casts the flag's text and checks it, naming the flag and the rule on failure."""
    def parse(text: str):
        try:
            value = cast(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be {kind}, got {text!r}") from None
        if not ok(value):
            raise argparse.ArgumentTypeError(f"{name} must be {rule}, got {value}")
        return value
    return parse


def int_in_range(name: str, low: int, high: int) -> Callable[[str], int]:
    """Parse an integer flag that must lie in ``[low, high]``."""
    return _checked(name, int, "an integer", lambda v: low <= v <= high, f"in [{low}, {high}]")


def non_negative_float(name: str) -> Callable[[str], float]:
    """Parse a float flag that must be finite and >= 0."""
    return _checked(name, float, "a number", lambda v: 0.0 <= v < float("inf"), ">= 0")


def positive_float(name: str) -> Callable[[str], float]:
    """Parse a float flag that must be finite and > 0."""
    return _checked(name, float, "a number", lambda v: 0.0 < v < float("inf"), "> 0")


def open_unit_float(name: str) -> Callable[[str], float]:
    """Parse a probability flag that must lie strictly between 0 and 1."""
    return _checked(name, float, "a number", lambda v: 0.0 < v < 1.0, "in (0, 1)")

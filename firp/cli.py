"""argparse value types shared by every command line: each error names the flag and the rule."""

from __future__ import annotations

import argparse
from typing import Callable


def int_in_range(name: str, low: int, high: int) -> Callable[[str], int]:
    """Parse an integer flag that must lie in ``[low, high]``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be an integer, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{name} must be in [{low}, {high}], got {value}")
        return value
    return parse


def non_negative_float(name: str) -> Callable[[str], float]:
    """Parse a float flag that must be finite and >= 0."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {text!r}") from None
        if not 0.0 <= value < float("inf"):
            raise argparse.ArgumentTypeError(f"{name} must be >= 0, got {value}")
        return value
    return parse


def open_unit_fraction(name: str) -> Callable[[str], float]:
    """Parse a fraction flag that must lie strictly between 0 and 1."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {text!r}") from None
        if not 0.0 < value < 1.0:
            raise argparse.ArgumentTypeError(f"{name} must be in (0, 1), got {value}")
        return value
    return parse

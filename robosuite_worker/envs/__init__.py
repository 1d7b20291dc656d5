"""Environments written in robosuite's style for tasks robosuite does not ship (importing registers them)."""

from robosuite_worker.envs.stack_three import StackThree

__all__ = ["StackThree"]

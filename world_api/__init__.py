"""The HTTP API every world serves: start a seeded episode, execute plans on it, delete it.

One implementation of the routes, request and response schemas, the episode store and the
one-thread runner, shared by our MuJoCo world (``sim_worker``) and the robosuite world
(``robosuite_worker``), so a planner talks to either the same way (``planner_client.clients.SimClient``).
A world plugs in as a :class:`~world_api.backend.WorldBackend`: the tasks it has, how an episode
begins and how a plan runs. Imports the shared core only (no torch, no MuJoCo, no world).
"""

from world_api.app import create_world_app
from world_api.backend import EpisodeStart, Outcome, WorldBackend

__all__ = ["EpisodeStart", "Outcome", "WorldBackend", "create_world_app"]

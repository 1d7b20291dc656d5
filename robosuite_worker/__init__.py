"""A second world that no one here wrote: robosuite (MimicGen's simulator) behind the API every world serves.

Runs in its own environment (``make robosuite-install``: robosuite 1.5.2 on the MuJoCo version it
supports, beside our world's pinned MuJoCo 4.0.0), so neither world's physics drifts under the
other's recorded datasets. Imports the shared core and the world API; no torch, no planner, no method.
"""

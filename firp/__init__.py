"""firp: future-predictive success-or-failure classification of robot action plans.

The method package. Its ``contract`` and ``episodes`` modules are numpy/h5py only so that the
sim worker and the planner client can share them without torch; the model, losses and training
live in torch-only submodules.
"""

"""The shared core every part imports: the plan contract, the episode (HDF5) format, the HTTP error
shape, CLI argument types and the bundle format. Torch-free and MuJoCo-free, and it imports no other
part, so a sim worker, a planner and a scoring service can each be installed and run without the
others' dependencies (``tests/test_layers.py`` checks it, module by module)."""

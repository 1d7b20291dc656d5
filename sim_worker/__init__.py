"""The MuJoCo world: scene, tasks, simulated perception, plan executor, dataset collection (no torch)."""

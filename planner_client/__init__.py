"""The TAMP-style planner and the replan-until-success loop (no torch)."""

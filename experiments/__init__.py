"""Research analyses: what the product's numbers rest on, apart from the product.

Each module is one analysis, run from the repository's root as ``python -m experiments.<name>``; its
docstring has the exact commands, and its results are committed under ``docs/results/``:

    planner_rates          how often the planner alone succeeds, and whether another block order rescues it
    replan_threshold       every candidate of a scene scored and executed: the loop's rule replayed for any threshold
    outcome_sensitivity    how many outcomes flip under a millimetre's change of the scene (the ceiling of any scorer)
    outcome_predictability how much of the outcome scene descriptions predict (logistic regression, boosting)
    grasp_frame_scorer     a classifier on the plan's grasp-frame description as a loop scorer
    prediction_gap         a trained FIRP's head on its predictions vs on the real executed frames
    head_temperature       the attention head's temperature L
    open_loop_sampling     the open loop trained on samples vs on means
    tcr_ablation           the TCR ablation figures of an evaluation run

Speed and scale benchmarks are in ``benchmarks/``.
"""

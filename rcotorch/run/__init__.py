"""Running refinements: scenarios, the runner with its monitoring, outputs and figures, sweeps, tuning,
``refine`` for a graph built in Python, and the command line.
"""

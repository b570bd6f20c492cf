"""The blocks a graph is made of: the base class and simple maps, LTI systems, nonlinear state-space
models, sources, and the basis features of an estimator's regressors.
"""

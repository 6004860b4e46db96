"""Sparse pose-graph optimization: Cartographer's OptimizationProblem2D without Ceres.

``problem`` defines the variables and residual blocks and evaluates them,
``levenberg_marquardt`` is the solver (``optimize``), ``block_cholesky`` the
linear algebra of one step. Callers need only what is re-exported here.
"""
from carto_cli.mapping.optimization.levenberg_marquardt import OptimizationResult, OptimizationSummary, optimize
from carto_cli.mapping.optimization.problem import NodePairs, residuals

__all__ = ["NodePairs", "OptimizationResult", "OptimizationSummary", "optimize", "residuals"]

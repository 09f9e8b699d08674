"""Robustness of a trained model to sensor failures and corruptions (``occkit robustness``).

The corruptions themselves are applied by the dataset (:mod:`occkit.data.corruptions`); this package picks the cases
(:mod:`~occkit.robustness.suite`), runs and caches them (:mod:`~occkit.robustness.run`) and scores and reports them
(:mod:`~occkit.robustness.report`).
"""

from occkit.robustness.run import run_robustness
from occkit.robustness.suite import SUITES, Case, parse_suite

__all__ = ["run_robustness", "parse_suite", "Case", "SUITES"]

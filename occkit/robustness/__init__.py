"""Robustness of a trained model to sensor failures and corruptions (``occkit robustness``).

The corruptions themselves are applied by the dataset (:mod:`occkit.data.corruptions`); this package picks the cases
(:mod:`~occkit.robustness.suite`), runs them (:mod:`~occkit.robustness.run`), caches each case's scores under a
fingerprint of everything they depend on (:mod:`~occkit.robustness.cache`) and scores and reports them
(:mod:`~occkit.robustness.report`).
"""

from occkit.robustness.run import run_robustness
from occkit.robustness.suite import SUITES, Case, parse_suite

__all__ = ["run_robustness", "parse_suite", "Case", "SUITES"]

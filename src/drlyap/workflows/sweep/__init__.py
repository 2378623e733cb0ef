"""Sweeps: train, verify and evaluate every combination of seeds x radii x risk levels x methods.

* :mod:`~drlyap.workflows.sweep.grid` -- the grid (:class:`SweepSpec`) and its parsing;
* :mod:`~drlyap.workflows.sweep.task` -- one combination (:func:`run_combination`);
* :mod:`~drlyap.workflows.sweep.backends` -- local processes or Ray;
* :mod:`~drlyap.workflows.sweep.driver` -- :func:`run_sweep` (resumable), the tables and the summary.
"""

from drlyap.workflows.sweep.backends import Backend, LocalBackend, RayBackend, make_backend
from drlyap.workflows.sweep.driver import finished_row, format_row, format_summary, run_sweep, summarise, write_tables
from drlyap.workflows.sweep.grid import (
    METHODS,
    Combination,
    SweepError,
    SweepSpec,
    parse_methods,
    parse_seeds,
    parse_values,
)
from drlyap.workflows.sweep.task import run_combination, verification_row

__all__ = ["METHODS", "Backend", "Combination", "LocalBackend", "RayBackend", "SweepError", "SweepSpec", "finished_row",
           "format_row", "format_summary", "make_backend", "parse_methods", "parse_seeds", "parse_values",
           "run_combination", "run_sweep", "summarise", "verification_row", "write_tables"]

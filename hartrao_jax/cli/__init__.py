"""Command line: ``hartrao-jax COMMAND``, one module per verb group; the only layer that prints.

* ``_base``: the click group ``main`` (verbs loaded lazily by name, :data:`._base.VERBS`),
  ``run`` (the console command: ``main`` without Python's shutdown), one-line errors, the
  console, the result table
* ``_pipeline``: simulate, preprocess, fit, demo
* ``_campaign``: schedule, fit-joint, gravity, sensitivity, fit-dask, fit-stream
* ``_surface``: surface, report
* ``_diagnose``: diagnose, prove
* ``_import``: import (PTX, XYZ, E57 exports)
* ``_checks``: option and input validation before any work
* ``_tables``: terminal summaries
"""

from ._base import VERBS, UserError, command, main, print_fit_table, run

__all__ = ["UserError", "VERBS", "command", "main", "print_fit_table", "run"]

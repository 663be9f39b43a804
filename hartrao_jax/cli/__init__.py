"""Command line: ``hartrao-jax COMMAND``, one module per verb group; the only layer that prints.

* ``_base``: the click group ``main``, one-line errors, the console, the result table
* ``_pipeline``: simulate, preprocess, fit, demo
* ``_campaign``: schedule, fit-joint, gravity, sensitivity, fit-dask, fit-stream
* ``_surface``: surface, report
* ``_diagnose``: diagnose, prove
* ``_import``: import (PTX, XYZ, E57 exports)
* ``_checks``: option and input validation before any work
"""

from . import _campaign, _diagnose, _pipeline, _surface  # noqa: F401  (register the verbs)
from ._base import UserError, command, main, print_fit_table
from ._import import import_command

main.add_command(import_command)

__all__ = ["UserError", "command", "import_command", "main", "print_fit_table"]

"""hartrao-jax: differentiable Gauss-Helmert adjustment of radio-telescope reflectors from
terrestrial laser scans.

The pipeline, in the order data flows:

* ``campaign/``: :func:`load_campaign`, :func:`read_scan`, :func:`write_campaign`
* ``geometry/``, ``physics/`` (:data:`EFFECTS`, :data:`INSTRUMENT`), ``model/`` (:func:`make_model`)
* ``solver/``: :func:`gauss_helmert`, :func:`robust_gauss_helmert`, :func:`gauss_helmert_batch`
* ``preprocess/``, ``fit/``: :func:`fit_scan`, :func:`fit_campaign`, :func:`write_fit`
* ``surface/``, ``diagnose/``, ``simulate/`` (:func:`simulate_campaign`), ``prove/``,
  ``sensitivity/``, ``report/``, ``cli/``: see ``ARCHITECTURE.md``

Importing the package turns on JAX's float64 (``jax_enable_x64``): the adjustment needs it.
It also adds XLA's CPU options of ``_config.XLA_FLAGS`` to ``$XLA_FLAGS`` (YNNPACK fusions off:
faster here), unless that variable already sets them.
"""

from ._config import enable_x64 as _enable_x64
from ._config import set_xla_flags as _set_xla_flags

_enable_x64()
_set_xla_flags()

from .campaign import (  # noqa: E402
    Campaign,
    CampaignError,
    ScanData,
    ScanMeta,
    load_campaign,
    read_scan,
    write_campaign,
)
from .fit import CampaignFit, ScanFit, fit_campaign, fit_json, fit_scan, write_fit  # noqa: E402
from .model import ModelError, ParaboloidModel, make_model, parse_model  # noqa: E402
from .physics import EFFECTS, EXTENDED, INSTRUMENT, SIMPLIFIED  # noqa: E402
from .simulate import CLASSES, PRESETS, parse_effects, simulate_campaign, simulate_scan  # noqa: E402
from .solver import GHResult, gauss_helmert, gauss_helmert_batch, robust_gauss_helmert  # noqa: E402

simulate = simulate_campaign

__version__ = "0.1.0"

__all__ = [
    "Campaign", "CampaignError", "CampaignFit", "EFFECTS", "EXTENDED", "GHResult", "INSTRUMENT",
    "ModelError", "ParaboloidModel", "SIMPLIFIED", "ScanData", "ScanFit", "ScanMeta",
    "fit_campaign", "fit_json", "fit_scan", "gauss_helmert", "gauss_helmert_batch",
    "load_campaign", "make_model", "parse_model", "read_scan", "robust_gauss_helmert",
    "write_campaign", "write_fit", "CLASSES", "PRESETS", "parse_effects", "simulate",
    "simulate_campaign", "simulate_scan",
]

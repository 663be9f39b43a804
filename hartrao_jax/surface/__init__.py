"""The surface: cycle averaging and panels from a fit, disturbed lines, local deformations,
the gravity model over elevation."""

from ._disturbed import detect_disturbed_campaign
from ._gravity import GravityModel, gravity_model, write_gravity
from ._local import find_local_deformations
from ._surface import (
    SurfaceConfig,
    SurfaceResult,
    surface_campaign,
    surface_from_fit_dir,
    write_surface,
)

__all__ = [
    "detect_disturbed_campaign",
    "find_local_deformations",
    "gravity_model",
    "GravityModel",
    "surface_campaign",
    "surface_from_fit_dir",
    "SurfaceConfig",
    "SurfaceResult",
    "write_gravity",
    "write_surface",
]

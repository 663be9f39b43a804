"""Frames and shapes: rotations, pointing -> telescope axes and gravity, reflector coordinates,
the paraboloid, panels and panel cells, Zernike polynomials."""

from ._geometry import (
    face_of,
    panel_cells,
    panel_geometry,
    panel_ids,
    paraboloid_deviation,
    pointing_gravity,
    polar_to_cartesian,
    rot_x,
    rot_y,
    rot_z,
    scanner_to_telescope,
    square_cells,
    zernike,
    zernike_columns,
)

__all__ = [
    "face_of",
    "panel_cells",
    "square_cells",
    "panel_geometry",
    "panel_ids",
    "paraboloid_deviation",
    "pointing_gravity",
    "polar_to_cartesian",
    "rot_x",
    "rot_y",
    "rot_z",
    "scanner_to_telescope",
    "zernike",
    "zernike_columns",
]

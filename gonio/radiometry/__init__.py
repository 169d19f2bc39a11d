"""Radiometry core: frames and angles, solid angles, irradiance, photometric conversion.

Units: radians, metres, W/(sr m^2) for radiance, W/m^2 for irradiance, W/sr for
intensity.  Every function is vectorised over leading array dimensions, in float64.
"""

from gonio.radiometry.emitters import (
    irradiance_disk,
    irradiance_point,
    irradiance_polygon,
    irradiance_rectangle,
    rectangle_vertices,
    solid_angle_cap,
    solid_angle_disk,
    solid_angle_element,
    solid_angle_polygon,
    solid_angle_rectangle,
)
from gonio.radiometry.frames import (
    angle_between,
    as_vectors,
    cos_theta,
    direction_to_spherical,
    directions_from_half_diff,
    dot,
    frame_from_normal,
    half_diff_from_directions,
    look_along_rotation,
    look_at_rotation,
    normalize,
    reflect,
    rotation_about,
    rotation_angle,
    spherical_to_direction,
    to_local,
    to_world,
)

__all__ = [
    "irradiance_disk",
    "irradiance_point",
    "irradiance_polygon",
    "irradiance_rectangle",
    "rectangle_vertices",
    "solid_angle_cap",
    "solid_angle_disk",
    "solid_angle_element",
    "solid_angle_polygon",
    "solid_angle_rectangle",
    "angle_between",
    "as_vectors",
    "cos_theta",
    "direction_to_spherical",
    "directions_from_half_diff",
    "dot",
    "frame_from_normal",
    "half_diff_from_directions",
    "look_along_rotation",
    "look_at_rotation",
    "normalize",
    "reflect",
    "rotation_about",
    "rotation_angle",
    "spherical_to_direction",
    "to_local",
    "to_world",
]

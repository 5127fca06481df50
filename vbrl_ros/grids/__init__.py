"""Voxel grids around the sensor: which voxel and sub-cell each point falls in.

:mod:`.base` (what every grid shares), :mod:`.cartesian` (the paper's grid),
:mod:`.polar` (rings x sectors, heading-robust), :mod:`.kinds` (the grid a
configuration names).
"""

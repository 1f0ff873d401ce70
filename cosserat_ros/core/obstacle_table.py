"""The table of obstacles the compiled step reads: one row of float64 per obstacle, whose
fields have names (:data:`OBSTACLE`) and whose columns the kernels read by the offsets
below. :class:`.obstacles.ObstacleSet` writes it by name; :mod:`.contact` has the physics.
This module imports no ROS package."""
from __future__ import annotations

import numpy as np

__all__ = ['SHAPES', 'OBSTACLE', 'WIDTH', 'records']

#: shape codes of column ``SHAPE``
SHAPES = {'plane': 0, 'sphere': 1, 'box': 2, 'capsule': 3, 'cylinder': 4, 'mesh': 5}

#: one obstacle, by name: the layout of a row of ``Control.obstacles``, whose float64
#: columns the compiled code reads by the offsets below (``table.view(OBSTACLE)``, or
#: :func:`records`, gives the fields by name)
OBSTACLE = np.dtype([
    ('shape', 'f8'),               # a code of SHAPES
    ('position', 'f8', 3),         # c [m]
    ('rotation', 'f8', (3, 3)),    # R, row-major (world = c + R p)
    ('velocity', 'f8', 3),         # linear velocity [m/s]
    ('omega', 'f8', 3),            # angular velocity [rad/s], world frame
    ('params', 'f8', 3),           # radius / half extents / (radius, half length) [m]
    ('mu_s', 'f8'),                # static friction coefficient
    ('mu_k', 'f8'),                # kinetic friction coefficient
    ('field', 'f8'),               # row of Control.sdf_meta (mesh)
    ('reach', 'f8'),               # radius of a sphere about c that holds it (0: a plane) [m]
    ('speed', 'f8'),               # the fastest any point of it within reach moves [m/s]
])


def _column(name: str) -> int:
    return OBSTACLE.fields[name][1] // 8


# the first column of each field in an obstacle row
SHAPE, POS, ROT, VEL, OMEGA = (_column(f) for f in ('shape', 'position', 'rotation',
                                                    'velocity', 'omega'))
PARAM, MU_S, MU_K, FIELD, REACH, SPEED = (_column(f) for f in ('params', 'mu_s', 'mu_k',
                                                              'field', 'reach', 'speed'))
WIDTH = OBSTACLE.itemsize // 8


def records(table: np.ndarray) -> np.ndarray:
    """The rows of an obstacle table (n, :data:`WIDTH`, C-contiguous float64, as
    ``Control.obstacles`` is) as n records of :data:`OBSTACLE`, a view: writing a field
    writes the table."""
    if table.dtype != np.float64 or table.ndim != 2 or table.shape[1] != WIDTH \
            or not table.flags.c_contiguous:
        raise ValueError(f'an obstacle table is C-contiguous float64 (n, {WIDTH}), got '
                         f'{table.dtype} {table.shape}')
    return table.view(OBSTACLE).reshape(-1)

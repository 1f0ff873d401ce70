"""What the node's run-time parameters must satisfy together, beyond each value's own
declaration (:func:`.params.check_value`): the wind within ``max_wind``, a valid material
and air, and on the explicit solver ``dt`` within the critical step of the material."""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

from ..core.air import Air
from ..core.material import Material
from . import scene
from .params import AIR_KEYS, ConfigError, MATERIAL_KEYS, wind as checked_wind

__all__ = ['check_together', 'material_and_air']


def check_together(node, new: dict) -> None:
    """ConfigError unless ``new`` (name -> value, one set-parameters call) keeps the
    wind within max_wind (a lowered max_wind below the standing air.wind too), the
    material and the air valid and, on the explicit solver, dt within the critical step
    of the material (:meth:`ClothSimulator.critical_dt`)."""
    sim = node.sim
    max_wind = new.get('max_wind', node.inputs.max_wind)
    if 'air.wind' in new:
        checked_wind(new['air.wind'], max_wind)
    elif 'max_wind' in new and float(np.linalg.norm(node.inputs.steady_wind)) > max_wind:
        raise ConfigError(f'max_wind {max_wind:g} m/s is below the standing air.wind '
                          f'({np.linalg.norm(node.inputs.steady_wind):.3g} m/s): lower '
                          'air.wind first, or both together')
    material, _ = material_and_air(node, new)
    dt = new.get('dt', sim.dt)
    if not node.implicit and (material != sim.material or dt != sim.dt):
        try:
            crit = sim.critical_dt(material)
        except (ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
            raise ConfigError(f'no stable step found for this material '
                              f'({type(exc).__name__}: {exc})') from None
        if not dt <= crit:                   # (a NaN limit refuses too)
            raise ConfigError(f'dt = {dt:.3g} s would exceed the critical step '
                              f'{crit:.3g} s of this mesh and material')


def material_and_air(node, new: dict) -> Tuple[Material, Optional[Air]]:
    """The material and the air (None: off) of ``node`` with the values of ``new`` in;
    ConfigError if invalid."""
    mat = {k: new.get('material.' + k, getattr(node.sim.material, k)) for k in MATERIAL_KEYS}
    coef = {k: new.get('air.' + k, node.get_parameter('air.' + k).value) for k in AIR_KEYS}
    try:
        return Material(**mat), scene.build_air(
            new.get('air.enabled', node.get_parameter('air.enabled').value), coef)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None

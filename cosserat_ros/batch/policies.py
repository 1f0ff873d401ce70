"""Policies shipped for ``policy: {script: 'cosserat_ros.batch.policies:<name>'}``.

A script policy is ``f(sim, rng, episode)``: ``sim`` the episode's simulator (its
``step`` records at the spec's rates and stops at the episode's end), ``rng`` the
episode's generator, ``episode`` the planned :class:`.spec.Episode`. It may be any
function importable on every worker; these are examples as much as tools.
"""
from __future__ import annotations

import numpy as np

__all__ = ['gusts']

#: [s] how long each gust lasts
GUST_PERIOD = 0.5
#: a gust's speed about the mean wind, as a fraction of the mean's speed (uniform +-)
GUST_SPREAD = 0.5


def gusts(sim, rng: np.random.Generator, episode) -> None:
    """Wind in gusts about the episode's steady wind (``air.wind``): every
    :data:`GUST_PERIOD` seconds a new wind, the mean plus a uniform draw of up to
    :data:`GUST_SPREAD` times its speed on each axis, as ``flag_demo`` blows on
    ``~/wind``. Needs ``air.enabled``."""
    if sim.air is None:
        raise ValueError('the gusts policy needs air.enabled: true')
    mean = np.array(sim.wind, dtype=float)
    spread = GUST_SPREAD * max(float(np.linalg.norm(mean)), 1.0)
    per = max(1, int(round(GUST_PERIOD / sim.dt)))
    while sim.remaining_steps > 0:
        sim.wind = mean + rng.uniform(-spread, spread, 3)
        sim.step(per)

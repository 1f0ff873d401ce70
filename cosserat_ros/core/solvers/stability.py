"""The explicit update's stability limit: the critical time step of a mesh and material.

The highest angular frequency omega_max of the system linearised at a state is found by
Lanczos iteration on ``M^-1/2 K M^-1/2`` (``K v`` from central differences of the internal
force), and the damped symplectic Euler limit (:func:`stability_limit`) is applied. For
membranes omega_max ~ 2 c / h (c = sqrt(6 zeta / mu)), giving the rule of thumb
``dt <~ 0.8 h / c`` of doc/theory.md section 7; bending adds ~ sqrt(D / mu) (k / h)^2 on fine
meshes. The critical dt is ``CRITICAL_DT_SAFETY`` (0.8) times that linear limit, because
strained states pump energy into the highest modes near it (constants.py has the
measurement).
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from ..constants import CRITICAL_DT_SAFETY

__all__ = ['stability_limit', 'max_eigenvalue', 'max_eigenpair', 'critical_dt']


def stability_limit(omega_max: float, gamma_max: float) -> float:
    """Largest stable dt of the damped symplectic Euler update for a mode of angular
    frequency omega with damping rate gamma = rho/mu: the Jury conditions of
    ``x'' = -omega^2 x - gamma x'`` give ``omega^2 dt^2 + 2 gamma dt < 4`` and
    ``gamma dt < 2``, i.e. ``dt < (sqrt(gamma^2 + 4 omega^2) - gamma) / omega^2``."""
    if omega_max <= 0:
        return np.inf if gamma_max <= 0 else 2.0 / gamma_max
    return (np.sqrt(gamma_max ** 2 + 4.0 * omega_max ** 2) - gamma_max) / omega_max ** 2


def max_eigenvalue(force: Callable[[np.ndarray, np.ndarray], None], mass: np.ndarray,
                   at: np.ndarray, h: float, iterations: int = 60, seed: int = 0) -> float:
    """omega_max^2 [1/s^2] of the free system linearised at positions ``at`` (n,3):
    Lanczos with full re-orthogonalisation, an upper estimate (largest Ritz value plus its
    residual). ``force(x, out)`` writes the internal force at x into out (n,3); ``h`` is
    the length scale of the finite-difference probe (the mean edge length)."""
    return max_eigenpair(force, mass, at, h, iterations, seed)[0]


def max_eigenpair(force: Callable[[np.ndarray, np.ndarray], None], mass: np.ndarray,
                  at: np.ndarray, h: float, iterations: int = 60, seed: int = 0,
                  start: np.ndarray = None):
    """:func:`max_eigenvalue` and its Ritz vector (3n,), starting from ``start`` (e.g. the
    vector of an earlier estimate for a nearby operator: a few iterations then suffice,
    and the residual term keeps the estimate an upper one) or from a random vector."""
    n3 = 3 * len(mass)
    minv_sqrt = np.repeat(1.0 / np.sqrt(mass), 3)
    f_p = np.empty_like(at)
    f_m = np.empty_like(at)

    def op(q):
        d = (minv_sqrt * q).reshape(-1, 3)
        eps = 1e-6 * h / max(np.abs(d).max(), 1e-300)
        force(at + eps * d, f_p)
        force(at - eps * d, f_m)
        return -minv_sqrt * ((f_p - f_m).ravel() / (2 * eps))

    k = min(iterations, n3)
    rng = np.random.default_rng(seed)
    Q = np.zeros((k + 1, n3))
    alpha = np.zeros(k)
    beta = np.zeros(k)
    q = rng.standard_normal(n3) if start is None else np.asarray(start, dtype=np.float64)
    Q[0] = q / np.linalg.norm(q)
    for j in range(k):
        w = op(Q[j])
        alpha[j] = Q[j] @ w
        w -= Q[:j + 1].T @ (Q[:j + 1] @ w)   # full re-orthogonalisation
        w -= Q[:j + 1].T @ (Q[:j + 1] @ w)
        beta[j] = np.linalg.norm(w)
        if beta[j] < 1e-12 * abs(alpha[j]) or j == k - 1:
            k = j + 1
            break
        Q[j + 1] = w / beta[j]
    T = np.diag(alpha[:k]) + np.diag(beta[:k - 1], 1) + np.diag(beta[:k - 1], -1)
    theta, s = np.linalg.eigh(T)
    return float(theta[-1] + abs(beta[k - 1] * s[-1, -1])), Q[:k].T @ s[:, -1]


def critical_dt(omega2_max: float, density: float, damping: float) -> float:
    """CRITICAL_DT_SAFETY times the damped limit for omega_max^2 [1/s^2]."""
    return CRITICAL_DT_SAFETY * stability_limit(math.sqrt(max(omega2_max, 0.0)),
                                                damping / density)

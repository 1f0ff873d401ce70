"""Strain stiffening of the membrane: a woven fabric is soft at small strain and locks up
past a few percent, when its yarns straighten (the knee of its measured stress-strain
curve). Registered as ``stiffening`` (:mod:`.registry`), off by default.

Energy
------
In each triangle t, with the Green strain ``eps_t`` of :mod:`.membrane` (its orthonormal
rest chart) and its size ``s_t = |eps_t| = sqrt(eps:eps) = sqrt(e11^2 + 2 e12^2 + e22^2)``:

    E_s = sum_t area_t W(eps_t),    W = k <s - s0>^2                     [J]

``k`` = ``stiffness`` [N/m], ``s0`` = ``knee`` [-]; ``<a> = max(a, 0)``. Zero below the
knee in every direction (so the small-strain membrane of the seed is untouched), C1
across it, and past it the added tension of a uniaxial Green strain e11 = s is
``dW/de11 = 2 k (s - s0)``: the stress-strain law a fit to a measured curve's upper
branch gives (2 k its slope, s0 where it starts).

Gradient
--------
``P = dW/deps = 2 k <s - s0> eps / s`` (a 2 x 2 tensor, ``dW = P : deps``), and as for
the membrane the corner gradients are ``[g_1 g_2] = F (area P) Dinv^T``, ``g_0 = -g_1 -
g_2``.

Hessian blocks
--------------
With ``e = (e11, e12, e22)``, ``M = diag(1, 2, 1)`` (``s^2 = e^T M e``) and, for s > s0,

    d2W/de2 = 2 k [ (s0 / s) (M e)(M e)^T / s^2 + (1 - s0 / s) M ]       (PSD)

the block of corner c is ``area L_c^T (d2W/de2) L_c + area (G_c P G_c^T) I_3`` with the
membrane's rows ``L_c`` (``de = L_c dx_c``) and ``G_c``; P's positive part is taken in the
second term, which leaves the block exact where P is positive semi-definite (a stretched
triangle) and makes every block PSD.
"""
from __future__ import annotations

import numpy as np

from .registry import Coefficient

__all__ = ['Stiffening']


def _strain(model, x):
    """(F (m,3,2), eps (m,2,2), the faces' Dinv (m,2,2), area (m,))."""
    f = model.faces
    c = f.corners
    e = np.stack([x[c[:, 1]] - x[c[:, 0]], x[c[:, 2]] - x[c[:, 0]]], axis=2)   # (m,3,2)
    F = e @ f.dinv
    eps = 0.5 * (np.einsum('tki,tkj->tij', F, F) - np.eye(2))
    return F, eps, f.dinv, f.area


def _size(eps):
    return np.sqrt(eps[:, 0, 0] ** 2 + 2.0 * eps[:, 0, 1] ** 2 + eps[:, 1, 1] ** 2)


def _rows(dinv):
    """G_c (m,3,2): the rows of dF = dx_c (x) G_c (G_0 = -G_1 - G_2)."""
    g = np.empty((len(dinv), 3, 2))
    g[:, 1] = dinv[:, 0]
    g[:, 2] = dinv[:, 1]
    g[:, 0] = -g[:, 1] - g[:, 2]
    return g


class Stiffening:
    """E = sum_t area_t stiffness <|eps_t| - knee>^2 (module docstring)."""

    name = 'stiffening'
    coefficients = (
        Coefficient('stiffness', default=0.0, unit='N/m', low=0.0, high=1e9,
                    text='Strain stiffening past the knee, W = k <|eps| - knee>^2 (0: off)'),
        Coefficient('knee', default=0.03, unit='-', low=0.0, high=1.0,
                    text='Green strain where the stiffening starts'))

    def active(self, c) -> bool:
        return c.stiffness > 0.0

    def energy(self, model, x, c):
        _, eps, _, area = _strain(model, x)
        over = np.maximum(_size(eps) - c.knee, 0.0)
        return float(np.sum(area * c.stiffness * over * over))

    def _stress(self, eps, c):
        """P = 2 k <s - s0> eps / s (m,2,2) and s (m,)."""
        s = _size(eps)
        over = np.maximum(s - c.knee, 0.0)
        ratio = np.where(over > 0.0, 2.0 * c.stiffness * over / np.maximum(s, 1e-300), 0.0)
        return ratio[:, None, None] * eps, s

    def gradient(self, model, x, c):
        F, eps, dinv, area = _strain(model, x)
        P, _ = self._stress(eps, c)
        g12 = F @ (area[:, None, None] * P) @ np.transpose(dinv, (0, 2, 1))    # (m,3,2)
        out = np.zeros_like(x)
        corners = model.faces.corners
        np.add.at(out, corners[:, 1], g12[:, :, 0])
        np.add.at(out, corners[:, 2], g12[:, :, 1])
        np.add.at(out, corners[:, 0], -g12[:, :, 0] - g12[:, :, 1])
        return out

    def hessian_blocks(self, model, x, c):
        F, eps, dinv, area = _strain(model, x)
        P, s = self._stress(eps, c)
        on = s > c.knee
        n = len(x)
        out = np.zeros((n, 3, 3))
        if not np.any(on):
            return out
        e = np.stack([eps[:, 0, 0], eps[:, 0, 1], eps[:, 1, 1]], axis=1)       # (m,3)
        me = e * np.array([1.0, 2.0, 1.0])
        ss = np.maximum(s, 1e-300)
        q = np.where(on, c.knee / ss, 0.0)
        H = 2.0 * c.stiffness * (q[:, None, None] / ss[:, None, None] ** 2
                                 * np.einsum('ti,tj->tij', me, me)
                                 + (1.0 - q)[:, None, None] * np.diag([1.0, 2.0, 1.0]))
        H[~on] = 0.0
        w, v = np.linalg.eigh(P)                    # P's positive part, for PSD blocks
        Pp = np.einsum('tij,tj,tkj->tik', v, np.maximum(w, 0.0), v)
        G = _rows(dinv)
        F1, F2 = F[:, :, 0], F[:, :, 1]
        for k in range(3):
            a, b = G[:, k, 0], G[:, k, 1]
            L = np.stack([a[:, None] * F1, 0.5 * (b[:, None] * F1 + a[:, None] * F2),
                          b[:, None] * F2], axis=1)                            # (m,3,3)
            blk = area[:, None, None] * np.einsum('tai,tab,tbj->tij', L, H, L)
            stress = area * np.einsum('ti,tij,tj->t', G[:, k], Pp, G[:, k])
            blk += stress[:, None, None] * np.eye(3)
            np.add.at(out, model.faces.corners[:, k], blk)
        return out

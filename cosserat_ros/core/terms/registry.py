"""The registry of energy terms: what the solvers, the energy report and the node iterate.

A term is an object with a ``name``, its ``coefficients`` (a tuple of
:class:`Coefficient`) and three methods, for a :class:`..model.Model`, positions ``x``
(n,3) [m] and its coefficient values ``c`` (:class:`Values`: ``c.k``)::

    energy(model, x, c)          -> float [J]
    gradient(model, x, c)        -> (n,3) [N], dE/dx
    hessian_blocks(model, x, c)  -> (n,3,3) [N/m], the per-vertex diagonal blocks of its
                                    Hessian (or their Gauss-Newton approximation), PSD

and optionally ``active(c) -> bool``: False where the coefficients make it vanish (a
stiffness of 0), so that the solvers skip it and a term off by default changes nothing.

:func:`register` adds one; every :class:`~cosserat_ros.core.simulator.ClothSimulator`
built afterwards carries it, with its coefficients' defaults unless given
(``ClothSimulator(..., terms={'tether': {'k': 50.0}})``, ``set_term``). Where it acts:

* the explicit step adds ``-gradient`` at each step's start positions to the applied
  force of that step (the symplectic Euler update, doc/theory.md section 6), one step
  per compiled call, and books its work as the term's energy, not as external work;
* the implicit solver adds ``-gradient`` to the internal force of its residual, the
  energy to the potential its line search minimises and the blocks to its
  preconditioner (its Hessian products are differences of the internal force, so they
  carry the term's whole Hessian);
* the energy report lists ``energy`` under the term's name and adds it to ``total``;
* the node declares ``terms.<name>.<coefficient>`` for each, at run time changeable.

The built-in terms (membrane, bending, coupling) are registered here too, as
:class:`Builtin`: their coefficients are :class:`..material.Material`'s, and the
compiled step computes them fused (the declared fast path); the others go through their
own ``gradient``.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
import re
from typing import Dict, List, Tuple

import numpy as np

__all__ = ['Coefficient', 'Values', 'Builtin', 'register', 'unregister', 'registered',
           'extra_terms', 'values_of', 'check_term', 'acting']


@dataclass(frozen=True)
class Coefficient:
    """A term's coefficient: its ``name`` (a Python identifier), ``default``, ``unit``,
    valid range ``[low, high]`` and a line of ``text``."""

    name: str
    default: float
    unit: str = ''
    low: float = -math.inf
    high: float = math.inf
    text: str = ''

    def check(self, value, term: str) -> float:
        """``value`` as a float within range, else ValueError naming ``term.name``."""
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer,
                                                            np.floating)):
            raise ValueError(f'{term}.{self.name} must be a number, got {value!r}')
        value = float(value)
        if not (math.isfinite(value) and self.low <= value <= self.high):
            raise ValueError(f'{term}.{self.name} must be a finite number in [{self.low:g}, '
                             f'{self.high:g}] {self.unit}, got {value!r}')
        return value


class Values(dict):
    """A term's coefficient values by name, also as attributes (``c.k``)."""

    def __getattr__(self, name):
        try:
            return self[name]
        except KeyError:
            raise AttributeError(name) from None


class Builtin:
    """A built-in term (one of :data:`..TERMS`'s modules): its coefficients are the
    material's (``c`` is :class:`..model.Coefficients`), and the compiled step computes it
    fused with the others."""

    builtin = True
    coefficients: Tuple[Coefficient, ...] = ()

    def __init__(self, name: str, module):
        self.name = name
        self.module = module

    def energy(self, model, x, c):
        return self.module.energy(model, c, x)

    def gradient(self, model, x, c):
        return self.module.gradient(model, c, x)

    def hessian_blocks(self, model, x, c):
        return self.module.hessian_blocks(model, c, x)


#: every registered term by name, the built-ins first
REGISTRY: Dict[str, object] = {}

_NAME = re.compile(r'[a-z][a-z0-9_]*')
#: names the energy report uses already
_TAKEN = ('kinetic', 'stretching', 'elastic', 'gravity', 'external_work', 'dissipated',
          'total')


def register(term):
    """Add ``term`` (module docstring) to the registry; returns it. A name already
    registered by an object of another class is refused (ValueError); the same class
    again replaces it (a module imported twice). Register before building the
    simulators (or the node) that should carry it."""
    name = getattr(term, 'name', None)
    if not isinstance(name, str) or not _NAME.fullmatch(name) or name in _TAKEN:
        raise ValueError(f'a term needs a name of lower-case letters, digits and _ (not '
                         f'one of {", ".join(_TAKEN)}), got {name!r}')
    for method in ('energy', 'gradient', 'hessian_blocks'):
        if not callable(getattr(term, method, None)):
            raise ValueError(f'term {name!r} has no {method}(model, x, c) method')
    coefs = tuple(getattr(term, 'coefficients', ()))
    seen = set()
    for c in coefs:
        if not isinstance(c, Coefficient) or not c.name.isidentifier() or c.name in seen:
            raise ValueError(f'term {name!r}: coefficients must be Coefficient objects with '
                             f'distinct identifier names, got {c!r}')
        seen.add(c.name)
        c.check(c.default, name)
    old = REGISTRY.get(name)
    if old is not None and (type(old) is not type(term) or getattr(old, 'builtin', False)):
        raise ValueError(f'a term named {name!r} is registered already ({old!r})')
    REGISTRY[name] = term
    return term


def unregister(name: str) -> None:
    """Remove the registered term ``name`` (not a built-in); KeyError if there is none."""
    if getattr(REGISTRY.get(name), 'builtin', False):
        raise ValueError(f'{name!r} is a built-in term')
    del REGISTRY[name]


def registered() -> List[str]:
    """The names of every registered term, built-ins first."""
    return list(REGISTRY)


def extra_terms() -> List[object]:
    """The registered terms that are not built in, in registration order."""
    return [t for t in REGISTRY.values() if not getattr(t, 'builtin', False)]


def acting(pairs) -> list:
    """The (term, values) pairs whose term acts with these values (``active``, if the
    term has one, says so)."""
    return [(t, c) for t, c in pairs if getattr(t, 'active', None) is None or t.active(c)]


def values_of(term, given=None) -> Values:
    """``term``'s coefficient values: its defaults, with ``given`` (name -> value)
    checked and put in; ValueError for an unknown name or a value out of range."""
    given = dict(given or {})
    known = {c.name: c for c in term.coefficients}
    unknown = sorted(set(given) - set(known))
    if unknown:
        raise ValueError(f'term {term.name!r} has no coefficient {", ".join(unknown)} (it has '
                         f'{", ".join(known) or "none"})')
    return Values({c.name: c.check(given.get(c.name, c.default), term.name)
                   for c in term.coefficients})


def check_term(term, model, x: np.ndarray, c, h: float = 1e-6, rtol: float = 1e-5):
    """A term's gradient against central differences of its energy, and its Hessian
    blocks against central differences of its gradient, at ``x``; returns the largest
    relative errors (gradient, blocks) and raises AssertionError above ``rtol``. For a
    new term's own tests; ``c`` may be a plain dict of its coefficients."""
    if isinstance(c, dict):
        c = Values(c)
    x = np.array(x, dtype=float)
    g = term.gradient(model, x, c)
    b = term.hessian_blocks(model, x, c)
    n = len(x)
    gd = np.zeros_like(g)
    bd = np.zeros_like(b)
    for i in range(n):
        for a in range(3):
            xp, xm = x.copy(), x.copy()
            xp[i, a] += h
            xm[i, a] -= h
            gd[i, a] = (term.energy(model, xp, c) - term.energy(model, xm, c)) / (2 * h)
            bd[i, :, a] = (term.gradient(model, xp, c)[i] - term.gradient(model, xm, c)[i]) / (
                2 * h)
    eg = float(np.abs(g - gd).max() / max(np.abs(gd).max(), 1e-300))
    eb = float(np.abs(b - bd).max() / max(np.abs(bd).max(), 1e-300))
    if eg > rtol or eb > rtol:
        raise AssertionError(f'term {term.name!r}: gradient error {eg:.2g}, blocks error '
                             f'{eb:.2g} (relative, at most {rtol:g})')
    return eg, eb

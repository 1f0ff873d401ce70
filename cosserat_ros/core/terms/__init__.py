"""The energy terms of the discrete Cosserat surface, one module each.

The internal force is minus the gradient of the discrete energy
``E = E_membrane + E_bending + E_coupling`` (doc/theory.md section 5, the variational route):

==================  ======================================================================
module              term
==================  ======================================================================
:mod:`.membrane`    constant-strain triangles, ``sum_t area_t zeta B(eps_t, eps_t)``
:mod:`.bending`     per-vertex jets, ``sum_i A_i xi B(kap_i, kap_i)`` + hourglass control
:mod:`.coupling`    ``sum_i A_i phi B(epsbar_i, kap_i)``
:mod:`.jet`         (shared) the jet along the normal and its exact adjoint
:mod:`.covariant`   the seed's route: a force without an energy (comparison only)
==================  ======================================================================

Every term module exposes, for a :class:`..model.Model`, its
:class:`..model.Coefficients` and positions ``x`` (n,3):

* ``energy(model, coeff, x) -> float`` [J];
* ``gradient(model, coeff, x) -> (n,3)`` [N], dE/dx;
* ``hessian_blocks(model, coeff, x) -> (n,3,3)`` [N/m], the per-vertex diagonal blocks
  of its Hessian (or their Gauss-Newton approximation), positive semi-definite.

``test/test_terms.py`` checks each against central differences of its own energy
(gradient) and of its own gradient (blocks).

To add a physical effect: a class with a name, its coefficients and these three methods
(taking ``(model, x, c)``, ``c`` its own coefficient values) and one
:func:`.registry.register` call; every solver, the energy report and the node then carry
it (:mod:`.registry`; ``test/test_term_registry.py`` adds one from outside the package).
"""
from . import bending, coupling, membrane
from .stiffening import Stiffening
from .registry import (Builtin, check_term, Coefficient, extra_terms, register, registered,
                       unregister, Values)

#: the variational terms, by name; the internal force is minus the sum of their gradients
TERMS = {'membrane': membrane, 'bending': bending, 'coupling': coupling}
for _name, _module in TERMS.items():
    register(Builtin(_name, _module))
register(Stiffening())                  # strain stiffening past a knee, off by default

__all__ = ['TERMS', 'Coefficient', 'Values', 'register', 'unregister', 'registered',
           'extra_terms', 'check_term']

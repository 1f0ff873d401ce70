"""Explicit SIMD vectors for the numba kernels: ``f64x4``, four float64 lanes in one register.

Why: the vertex pass works on short stencils (about 18 entries). Vectorised along the
stencil (what LLVM's auto-vectoriser does) each vertex pays for loop remainders, horizontal
sums and its per-vertex arithmetic (normal, stresses) on one lane. numba does not vectorise
across vertices by itself (it unrolls a constant lane loop before LLVM's loop vectoriser
can see it, and SLP vectorisation is off). These few intrinsics let a kernel say it
directly: one ``f64x4`` holds the same quantity of four vertices, and every operation on it
is one AVX instruction. The vertex pass (``lanes.vertex_lanes``) is written with
them; see ``docs/performance.md``.

The type lowers to LLVM's ``<4 x double>``; values stay in registers. Operations:

* ``vload(a, k)`` / ``vstore(a, k, v)``: lanes ``a.flat[k : k + 4]`` of a C-contiguous
  float64 array (no bounds check: the caller's layout guarantees the range);
* ``vload3(a, k)``: three vectors from the 12 values ``a.flat[k : k + 12]``, lane l of
  vector c being ``a.flat[k + 3 l + c]`` (four consecutive rows of an (n, 3) array, one
  vector per column: one 96-byte load and three shuffles instead of twelve scalar loads);
* ``splat(s)``: all lanes s; ``vset(s0, s1, s2, s3)``: from four scalars; ``lane(v, l)``;
* ``+ - * /`` and unary ``-`` (with a vector or a float on either side), ``vfma(a, b, c)``
  ``= a * b + c`` with one rounding, ``vsqrt``, and the builtin ``min(a, b)`` of two
  vectors or a vector and a float (lane-wise, ``llvm.minnum``).

Arithmetic is IEEE per lane, in the order written, with the one fast-math flag of
``compiled.STRICT`` (``contract``: a multiply feeding an add may become an FMA), so a lane
computes what the scalar kernels compute when written the same way. These functions only
work in compiled code.
"""
from __future__ import annotations

import operator

from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic, models, overload, register_model

__all__ = ['f64x4', 'LANES', 'vload', 'vload3', 'vstore', 'splat', 'vset', 'lane', 'vfma', 'vsqrt']

#: lanes of one vector (AVX: 4 x float64)
LANES = 4
_VT = ir.VectorType(ir.DoubleType(), LANES)


class F64x4(types.Type):
    """numba type of a vector of four float64 lanes."""

    def __init__(self):
        super().__init__(name='f64x4')


f64x4 = F64x4()


@register_model(F64x4)
class _F64x4Model(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, _VT)


def _check_array(a):
    if not (isinstance(a, types.Array) and a.dtype == types.float64 and a.layout == 'C'):
        raise TypeError(f'f64x4 load/store needs a C-contiguous float64 array, got {a}')


def _vector_pointer(context, builder, arrty, arr, k, vt=_VT):
    """Pointer to a.flat[k] as a pointer to the vector type ``vt``."""
    data = context.make_array(arrty)(context, builder, arr).data
    return builder.bitcast(builder.gep(data, [k]), vt.as_pointer())


@intrinsic
def vload(typingctx, a, k):
    """Lanes a.flat[k : k + 4]."""
    _check_array(a)

    def codegen(context, builder, sig, args):
        return builder.load(_vector_pointer(context, builder, sig.args[0], *args), align=8)
    return f64x4(a, k), codegen


_V12 = ir.VectorType(ir.DoubleType(), 3 * LANES)


@intrinsic
def vload3(typingctx, a, k):
    """(c0, c1, c2), lane l of c_j = a.flat[k + 3 l + j]: the columns of the four rows of
    an (n, 3) array that start at flat index k."""
    _check_array(a)

    def codegen(context, builder, sig, args):
        v = builder.load(_vector_pointer(context, builder, sig.args[0], *args, vt=_V12),
                         align=8)
        cols = [builder.shuffle_vector(v, ir.Constant(_V12, ir.Undefined),
                                       ir.Constant(ir.VectorType(ir.IntType(32), LANES),
                                                   [3 * l + j for l in range(LANES)]))
                for j in range(3)]
        return context.make_tuple(builder, sig.return_type, cols)
    return types.UniTuple(f64x4, 3)(a, k), codegen


@intrinsic
def vstore(typingctx, a, k, v):
    """a.flat[k : k + 4] = v."""
    _check_array(a)

    def codegen(context, builder, sig, args):
        builder.store(args[2], _vector_pointer(context, builder, sig.args[0], args[0], args[1]),
                      align=8)
        return context.get_dummy_value()
    return types.void(a, k, f64x4), codegen


def _from_scalars(builder, values):
    v = ir.Constant(_VT, ir.Undefined)
    for i, s in enumerate(values):
        v = builder.insert_element(v, s, ir.Constant(ir.IntType(32), i))
    return v


@intrinsic
def splat(typingctx, s):
    """(s, s, s, s)."""
    def codegen(context, builder, sig, args):
        s = context.cast(builder, args[0], sig.args[0], types.float64)
        return _from_scalars(builder, [s] * LANES)
    return f64x4(s), codegen


@intrinsic
def vset(typingctx, s0, s1, s2, s3):
    """(s0, s1, s2, s3)."""
    def codegen(context, builder, sig, args):
        return _from_scalars(builder, [context.cast(builder, a, t, types.float64)
                                       for a, t in zip(args, sig.args)])
    return f64x4(s0, s1, s2, s3), codegen


@intrinsic
def lane(typingctx, v, i):
    """Lane i of v."""
    def codegen(context, builder, sig, args):
        return builder.extract_element(args[0], args[1])
    return types.float64(f64x4, i), codegen


def _call_llvm(builder, name, args):
    fn = cgutils.get_or_insert_function(builder.module,
                                        ir.FunctionType(_VT, [_VT] * len(args)),
                                        f'llvm.{name}.v{LANES}f64')
    return builder.call(fn, args)


@intrinsic
def vfma(typingctx, a, b, c):
    """a * b + c with a single rounding."""
    def codegen(context, builder, sig, args):
        return _call_llvm(builder, 'fma', args)
    return f64x4(f64x4, f64x4, f64x4), codegen


@intrinsic
def vsqrt(typingctx, a):
    """Lane-wise square root."""
    def codegen(context, builder, sig, args):
        return _call_llvm(builder, 'sqrt', args)
    return f64x4(f64x4), codegen


def _binary(instr):
    @intrinsic
    def op(typingctx, a, b):
        def codegen(context, builder, sig, args):
            # 'contract' as in compiled.STRICT: a multiply feeding an add may become an FMA
            return getattr(builder, instr)(args[0], args[1], flags=('contract',))
        return f64x4(f64x4, f64x4), codegen
    return op


def _register_operator(pyop, impl):
    @overload(pyop)
    def _ov(a, b):
        if a is f64x4 and b is f64x4:
            return lambda a, b: impl(a, b)
        if a is f64x4 and isinstance(b, (types.Float, types.Integer)):
            return lambda a, b: impl(a, splat(b))
        if isinstance(a, (types.Float, types.Integer)) and b is f64x4:
            return lambda a, b: impl(splat(a), b)
        return None


for _pyop, _instr in ((operator.add, 'fadd'), (operator.sub, 'fsub'), (operator.mul, 'fmul'),
                      (operator.truediv, 'fdiv')):
    _register_operator(_pyop, _binary(_instr))



@intrinsic
def _vmin(typingctx, a, b):
    def codegen(context, builder, sig, args):
        return _call_llvm(builder, 'minnum', args)
    return f64x4(f64x4, f64x4), codegen


_register_operator(min, _vmin)


@intrinsic
def _vneg(typingctx, a):
    def codegen(context, builder, sig, args):
        return builder.fneg(args[0])
    return f64x4(f64x4), codegen


@overload(operator.neg)
def _neg(a):
    if a is f64x4:
        return lambda a: _vneg(a)
    return None

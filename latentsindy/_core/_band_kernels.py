"""LAPACK's banded Cholesky factorisation and solves (``dpbtrf``, ``dpbtrs``, upper
form), compiled, with LAPACK's arithmetic.

For a band of ``kd <= 64`` diagonals above the main one, LAPACK factorises column by
column (``dpbtf2``): the square root of the diagonal, the row beyond it scaled by its
reciprocal (``dscal``), and a rank-one update of the trailing triangle (``dsyr``, one
``daxpy`` per column). ``dpbtrs`` solves each right-hand side by two triangular solves
(``dtbsv``): forward by dot products (``ddot``), backward by ``daxpy``. The kernels
here do the same operations in the same order, and their vector operations are written
as LLVM IR (numba intrinsics, below) to be exactly those of OpenBLAS's SkylakeX kernels:
one rounding per fused multiply-add, every sum in the kernels' order. So their factors
and solutions are LAPACK's to the bit there, every number (a NaN where LAPACK has one,
its sign bit not guaranteed; ``tests/core/test_banded.py``), and the same on every CPU.
They take a fraction of LAPACK's time on stage one's bands (14-42 wide): LAPACK's calls
to its BLAS kernels cost more than their arithmetic on such short columns, and the
solves here take eight right-hand sides in one pass over the factor.

The intrinsics and the kernels share this file so that numba's cache, which checks the
kernels' own source file, is renewed when either changes. Offsets are in elements and
unchecked: the kernels keep them inside their arrays.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from llvmlite.ir import types as irtypes
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

MAX_KD = 64  # above, LAPACK factorises by blocks (dpotf2, dtrsm, dsyrk): left to it

_F64 = ir.DoubleType()
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)
_V8 = ir.VectorType(_F64, 8)
_ZERO8 = ir.Constant(_V8, [0.0] * 8)


def _declare(module, name, ret, args):
    try:
        return module.get_global(name)
    except KeyError:
        return ir.Function(module, ir.FunctionType(ret, args), name=name)


def _fma8(builder):
    return _declare(builder.module, "llvm.fma.v8f64", _V8, [_V8, _V8, _V8])


def _pointer(context, builder, arrty, arr, offset):
    """Address of element ``offset`` of a contiguous float64 array."""
    return builder.gep(context.make_array(arrty)(context, builder, arr).data, [offset])


def _pointer_suffix():
    """The masked intrinsics' name for a pointer to eight doubles: ``p0`` where llvmlite
    writes opaque pointers (LLVM 15 on), ``p0v8f64`` where it writes typed ones."""
    return "p0v8f64" if getattr(irtypes, "ir_layer_typed_pointers_enabled", True) else "p0"


def _load8(builder, address, mask=None):
    """Eight doubles from ``address``; with ``mask``, only the lanes it sets are read
    (the others 0)."""
    vector = builder.bitcast(address, _V8.as_pointer())
    if mask is None:
        return builder.load(vector, align=8)
    name = f"llvm.masked.load.v8f64.{_pointer_suffix()}"
    load = _declare(builder.module, name, _V8, [vector.type, _I32, mask.type, _V8])
    return builder.call(load, [vector, ir.Constant(_I32, 8), mask, _ZERO8])


def _store8(builder, value, address, mask=None):
    """Eight doubles to ``address``; with ``mask``, only the lanes it sets."""
    vector = builder.bitcast(address, _V8.as_pointer())
    if mask is None:
        builder.store(value, vector, align=8)
        return
    name = f"llvm.masked.store.v8f64.{_pointer_suffix()}"
    store = _declare(builder.module, name, ir.VoidType(), [_V8, vector.type, _I32, mask.type])
    builder.call(store, [value, vector, ir.Constant(_I32, 8), mask])


def _vector(ty):
    return isinstance(ty, types.Array) and ty.ndim == 1 and ty.layout == "C" and (
        ty.dtype == types.float64)


def _typed(arrays, offsets, scalars):
    """Whether an intrinsic's arguments are what it reads: contiguous float64 vectors,
    integer offsets, float64 scalars (else numba reports the call as untyped)."""
    return (all(_vector(a) for a in arrays)
            and all(isinstance(o, types.Integer) for o in offsets)
            and all(s == types.float64 for s in scalars))


def _broadcast(builder, scalar, width=8):
    vec = ir.VectorType(scalar.type, width)
    one = builder.insert_element(ir.Constant(vec, ir.Undefined), scalar, ir.Constant(_I32, 0))
    return builder.shuffle_vector(one, ir.Constant(vec, ir.Undefined),
                                  ir.Constant(ir.VectorType(_I32, width), [0] * width))


def _axpy_lanes(builder, y_at, alpha, x_at, skip):
    """``y = fma(alpha, x, y)`` on the eight doubles at ``y_at``, lanes ``skip..7``
    only (a masked load and store where ``skip`` is not 0)."""
    with builder.if_else(builder.icmp_signed("==", skip, ir.Constant(_I64, 0))) as (whole, part):
        for block, masked in ((whole, False), (part, True)):
            with block:
                mask = None
                if masked:
                    lanes = ir.Constant(ir.VectorType(_I64, 8), list(range(8)))
                    mask = builder.icmp_signed(">=", lanes, _broadcast(builder, skip))
                value = builder.call(_fma8(builder), [_broadcast(builder, alpha),
                                                      _load8(builder, x_at, mask),
                                                      _load8(builder, y_at, mask)])
                _store8(builder, value, y_at, mask)


@intrinsic
def axpy8(typingctx, y, y_at, alpha, x, x_at, skip):
    """``y[y_at + k] = fma(alpha, x[x_at + k], y[y_at + k])`` for ``skip <= k < 8``:
    OpenBLAS's ``daxpy`` on these elements (each its own fused multiply-add); the
    first ``skip`` lanes are neither read nor written."""
    if not _typed((y, x), (y_at, x_at, skip), (alpha,)):
        return None
    sig = types.void(y, y_at, alpha, x, x_at, skip)

    def codegen(context, builder, signature, args):
        y_arr, y_off, a, x_arr, x_off, n = args
        py = _pointer(context, builder, signature.args[0], y_arr, y_off)
        px = _pointer(context, builder, signature.args[3], x_arr, x_off)
        _axpy_lanes(builder, py, a, px, n)
        return context.get_dummy_value()

    return sig, codegen


def _row_sweep(emit):
    """An intrinsic ``(u, u_at, rows, at, stride, length, diagonal)`` whose IR is
    ``emit(builder, u_addr, rows_addr, stride, length, diagonal)``, the addresses those
    of ``u[u_at]`` and ``rows[at]``; its name and docstring are ``emit``'s."""
    def typer(typingctx, u, u_at, rows, at, stride, length, diagonal):
        if not _typed((u, rows), (u_at, at, stride, length), (diagonal,)):
            return None
        sig = types.void(u, u_at, rows, at, stride, length, diagonal)

        def codegen(context, builder, signature, args):
            u_arr, u_off, r_arr, r_off, step, n, d = args
            emit(builder, _pointer(context, builder, signature.args[0], u_arr, u_off),
                 _pointer(context, builder, signature.args[2], r_arr, r_off), step, n, d)
            return context.get_dummy_value()

        return sig, codegen

    typer.__name__, typer.__qualname__, typer.__doc__ = emit.__name__, emit.__name__, emit.__doc__
    return intrinsic(typer)


@_row_sweep
def forward_row8(builder, pu, pr, step, n, d):
    """One row of ``U' y = b`` for eight right-hand sides at once.

    ``rows[at + r * stride + c]`` is right-hand side ``c``'s value in row ``i - length +
    r`` (``r <= length``; row ``i`` last); ``u[u_at + e]`` for ``e < length`` is the
    factor's column ``i`` above the diagonal. Each right-hand side's row becomes
    ``(b_i - dot) / diagonal``, with the dot product in OpenBLAS's SkylakeX ``ddot``
    order: its first ``length & -16`` products in 32 lanes (eight-wide accumulators
    over 32-blocks, folded to four-wide ones for a last 16-block, then summed across
    accumulators and lanes), the rest one by one. ``length <= 64``.
    """
    fma8 = _fma8(builder)

    def row(e):  # the eight right-hand sides' values in row i - length + e
        return builder.gep(pr, [builder.mul(e, step)])

    def product(e, acc):  # fma(u[e], row e, acc), e an IR integer
        ue = _broadcast(builder, builder.load(builder.gep(pu, [e])))
        return builder.call(fma8, [ue, _load8(builder, row(e)), acc])

    const = lambda k: ir.Constant(_I64, k)  # noqa: E731
    n1 = builder.and_(n, const(-16))
    n32 = builder.and_(n, const(-32))
    wide = [cgutils.alloca_once_value(builder, _ZERO8) for _ in range(32)]  # lane 8g + l
    for block in (0, 32):
        with builder.if_then(builder.icmp_signed(">", n32, const(block))):
            for lane, slot in enumerate(wide):
                builder.store(product(const(block + lane), builder.load(slot)), slot)
    # fold each eight-wide accumulator into a four-wide one: lane 4g + l
    narrow = [cgutils.alloca_once_value(builder, builder.fadd(
        builder.load(wide[8 * g + lane]), builder.load(wide[8 * g + 4 + lane])))
        for g in range(4) for lane in range(4)]
    with builder.if_then(builder.icmp_signed("!=", n1, n32)):
        for lane, slot in enumerate(narrow):
            e = builder.add(n32, const(lane))
            builder.store(product(e, builder.load(slot)), slot)
    acc = [builder.load(slot) for slot in narrow]
    lanes = [builder.fadd(builder.fadd(builder.fadd(acc[lane], acc[4 + lane]),
                                       acc[8 + lane]), acc[12 + lane]) for lane in range(4)]
    kernel = builder.fadd(builder.fadd(lanes[0], lanes[2]), builder.fadd(lanes[1], lanes[3]))
    dot = cgutils.alloca_once_value(builder, _ZERO8)
    with builder.if_then(builder.icmp_signed("!=", n1, const(0))):
        builder.store(kernel, dot)
    with cgutils.for_range_slice(builder, n1, n, const(1)) as (e, _):
        builder.store(product(e, builder.load(dot)), dot)
    last = row(n)
    value = builder.fdiv(builder.fsub(_load8(builder, last), builder.load(dot)),
                         _broadcast(builder, d))
    _store8(builder, value, last)


@_row_sweep
def backward_row8(builder, pu, pr, step, n, d):
    """One row of ``U x = y`` for eight right-hand sides at once: row ``i`` (at
    ``rows[at + length * stride:]``) becomes ``x_i = y_i / diagonal``, and the ``length``
    rows above it get ``fma(-x_i, u[u_at + e], y)`` (OpenBLAS's ``daxpy``)."""
    last = builder.gep(pr, [builder.mul(n, step)])
    x = builder.fdiv(_load8(builder, last), _broadcast(builder, d))
    _store8(builder, x, last)
    minus = builder.fneg(x)
    fma8 = _fma8(builder)
    with cgutils.for_range(builder, n) as loop:
        target = builder.gep(pr, [builder.mul(loop.index, step)])
        ue = _broadcast(builder, builder.load(builder.gep(pu, [loop.index])))
        _store8(builder, builder.call(fma8, [minus, ue, _load8(builder, target)]), target)


@njit(cache=True, nogil=True, error_model="numpy")
def factor_band(band, kd, n):
    """Overwrite the upper band (flattened in Fortran order, ``kd + 1`` rows by ``n``)
    with its Cholesky factor, as ``dpbtf2``; returns LAPACK's ``info`` (0, or the order
    of the leading minor that is not positive definite)."""
    if kd < 0:
        raise ValueError("factor_band takes a band of at least one row (kd >= 0)")
    ld = kd + 1
    # row j of the factor beyond the diagonal, from row[7]: the seven slots before it
    # keep the masked lanes' addresses of the topmost blocks inside the array
    row = np.zeros(kd + 8)
    for j in range(n):
        ajj = band[kd + j * ld]
        if ajj <= 0.0:  # as LAPACK: not for NaN
            return j + 1
        ajj = np.sqrt(ajj)
        band[kd + j * ld] = ajj
        kn = min(kd, n - 1 - j)
        if kn > 0:
            scale = 1.0 / ajj
            for t in range(kn):
                at = kd - 1 - t + (j + 1 + t) * ld
                value = band[at] * scale
                band[at] = value
                row[7 + t] = value
            for q in range(kn):  # column j + 1 + q of the trailing triangle: q + 1 rows
                if row[7 + q] != 0.0:
                    # by blocks of eight rows up from the diagonal, the topmost masked
                    # where it reaches above the triangle
                    bottom = kd - 7 + (j + 1 + q) * ld
                    for p in range(0, q + 1, 8):
                        axpy8(band, bottom - p, -row[7 + q], row, q - p, max(0, p + 7 - q))
    return 0


@njit(cache=True, nogil=True, error_model="numpy")
def solve_band(band, kd, n, rows, width):
    """Solve ``U'U x = b`` in place for the factor ``band`` (as :func:`factor_band`
    leaves it, ``kd <= MAX_KD``) and the right-hand sides ``rows`` (flattened ``n x
    width``, C order, ``width`` a multiple of 8), each as ``dpbtrs`` solves it."""
    if kd < 0 or kd > MAX_KD or width % 8:
        raise ValueError("solve_band takes 0 <= kd <= 64 and a width that is a multiple of 8")
    ld = kd + 1
    for i in range(n):
        length = min(i, kd)
        for g in range(0, width, 8):
            forward_row8(band, kd - length + i * ld, rows, (i - length) * width + g, width,
                         length, band[kd + i * ld])
    for i in range(n - 1, -1, -1):
        length = min(i, kd)
        for g in range(0, width, 8):
            backward_row8(band, kd - length + i * ld, rows, (i - length) * width + g, width,
                          length, band[kd + i * ld])


@njit(cache=True, nogil=True, error_model="numpy")
def solve_columns(band, kd, n, rhs, out):
    """:func:`solve_band` of the right-hand sides ``rhs`` (``n x m``, any layout) for
    the factor ``band``, into ``out`` (``n x m``): eight columns at a time."""
    m = rhs.shape[1]
    width = -(-m // 8) * 8
    rows = np.zeros(n * width)
    for i in range(n):
        for c in range(m):
            rows[i * width + c] = rhs[i, c]
    solve_band(band, kd, n, rows, width)
    for c in range(m):
        for i in range(n):
            out[i, c] = rows[i * width + c]


@njit(cache=True, nogil=True, error_model="numpy")
def factor_solve(band, kd, n, rhs, out):
    """:func:`factor_band` on ``band``, then :func:`solve_columns` of ``rhs`` into
    ``out``; returns ``info`` (``out`` untouched unless 0)."""
    info = factor_band(band, kd, n)
    if info == 0:
        solve_columns(band, kd, n, rhs, out)
    return info


@njit(cache=True, nogil=True, error_model="numpy")
def penalised(base, at, scale, which, values, kd, diagonal):
    """A copy of the band ``base`` (flattened in Fortran order, ``kd + 1`` rows) with
    ``scale[which] * values`` added at the positions ``at`` (each at most once) and
    then ``diagonal`` added to its main diagonal (row ``kd``): numpy's
    ``band[at] += scale[which] * values; band[kd] += diagonal``, in one call."""
    band = base.copy()
    for k in range(at.shape[0]):
        band[at[k]] += scale[which[k]] * values[k]
    for k in range(kd, band.shape[0], kd + 1):
        band[k] += diagonal
    return band

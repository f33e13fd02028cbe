"""Vector operations for the compiled band Cholesky (:mod:`._band_kernels`), written
as LLVM IR through numba intrinsics.

numba vectorises loops by its own judgement; these do exactly the vector operations
that the OpenBLAS kernels behind LAPACK's ``dpbtrf``/``dpbtrs`` do (one rounding per
fused multiply-add, every sum in the kernels' order), so the compiled factorisation and
solves give LAPACK's numbers to the bit. Offsets are in elements and unchecked: the
callers keep them inside their arrays.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

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


def _load8(builder, address, mask=None):
    if mask is None:
        return builder.load(builder.bitcast(address, _V8.as_pointer()), align=8)
    load = _declare(builder.module, "llvm.masked.load.v8f64.p0", _V8,
                    [address.type, _I32, mask.type, _V8])
    return builder.call(load, [address, ir.Constant(_I32, 8), mask, _ZERO8])


def _store8(builder, value, address, mask=None):
    if mask is None:
        builder.store(value, builder.bitcast(address, _V8.as_pointer()), align=8)
        return
    store = _declare(builder.module, "llvm.masked.store.v8f64.p0", ir.VoidType(),
                     [_V8, address.type, _I32, mask.type])
    builder.call(store, [value, address, ir.Constant(_I32, 8), mask])


def _broadcast(builder, scalar, width=8):
    vec = ir.VectorType(scalar.type, width)
    one = builder.insert_element(ir.Constant(vec, ir.Undefined), scalar, ir.Constant(_I32, 0))
    return builder.shuffle_vector(one, ir.Constant(vec, ir.Undefined),
                                  ir.Constant(ir.VectorType(_I32, width), [0] * width))


@intrinsic
def axpy8(typingctx, y, y_at, alpha, x, x_at, skip):
    """``y[y_at + k] = fma(alpha, x[x_at + k], y[y_at + k])`` for ``skip <= k < 8``:
    OpenBLAS's ``daxpy`` on these elements (each its own fused multiply-add); the
    first ``skip`` lanes are neither read nor written."""
    sig = types.void(y, y_at, alpha, x, x_at, skip)

    def codegen(context, builder, signature, args):
        y_arr, y_off, a, x_arr, x_off, n = args
        py = _pointer(context, builder, signature.args[0], y_arr, y_off)
        px = _pointer(context, builder, signature.args[3], x_arr, x_off)
        with builder.if_else(builder.icmp_signed("==", n, ir.Constant(_I64, 0))) as (whole, part):
            with whole:
                value = builder.call(_fma8(builder), [_broadcast(builder, a), _load8(builder, px),
                                                      _load8(builder, py)])
                _store8(builder, value, py)
            with part:
                lanes = ir.Constant(ir.VectorType(_I64, 8), list(range(8)))
                mask = builder.icmp_signed(">=", lanes, _broadcast(builder, n))
                value = builder.call(_fma8(builder), [_broadcast(builder, a),
                                                      _load8(builder, px, mask),
                                                      _load8(builder, py, mask)])
                _store8(builder, value, py, mask)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def forward_row8(typingctx, u, u_at, rows, at, stride, length, diagonal):
    """One row of ``U' y = b`` for eight right-hand sides at once.

    ``rows[at + r * stride + c]`` is right-hand side ``c``'s value in row ``i - length +
    r`` (``r <= length``; row ``i`` last); ``u[u_at + e]`` for ``e < length`` is the
    factor's column ``i`` above the diagonal. Each right-hand side's row becomes
    ``(b_i - dot) / diagonal``, with the dot product in OpenBLAS's SkylakeX ``ddot``
    order: its first ``length & -16`` products in 32 lanes (eight-wide accumulators
    over 32-blocks, folded to four-wide ones for a last 16-block, then summed across
    accumulators and lanes), the rest one by one. ``length <= 64``.
    """
    sig = types.void(u, u_at, rows, at, stride, length, diagonal)

    def codegen(context, builder, signature, args):
        u_arr, u_off, r_arr, r_off, step, n, d = args
        pu = _pointer(context, builder, signature.args[0], u_arr, u_off)
        pr = _pointer(context, builder, signature.args[2], r_arr, r_off)
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
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def backward_row8(typingctx, u, u_at, rows, at, stride, length, diagonal):
    """One row of ``U x = y`` for eight right-hand sides at once: row ``i`` (at
    ``rows[at + length * stride:]``) becomes ``x_i = y_i / diagonal``, and the ``length``
    rows above it get ``fma(-x_i, u[u_at + e], y)`` (OpenBLAS's ``daxpy``)."""
    sig = types.void(u, u_at, rows, at, stride, length, diagonal)

    def codegen(context, builder, signature, args):
        u_arr, u_off, r_arr, r_off, step, n, d = args
        pu = _pointer(context, builder, signature.args[0], u_arr, u_off)
        pr = _pointer(context, builder, signature.args[2], r_arr, r_off)
        last = builder.gep(pr, [builder.mul(n, step)])
        x = builder.fdiv(_load8(builder, last), _broadcast(builder, d))
        _store8(builder, x, last)
        minus = builder.fneg(x)
        fma8 = _fma8(builder)
        with cgutils.for_range(builder, n) as loop:
            e = loop.index
            target = builder.gep(pr, [builder.mul(e, step)])
            ue = _broadcast(builder, builder.load(builder.gep(pu, [e])))
            _store8(builder, builder.call(fma8, [minus, ue, _load8(builder, target)]), target)
        return context.get_dummy_value()

    return sig, codegen

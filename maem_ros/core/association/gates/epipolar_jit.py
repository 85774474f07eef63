"""The numba building blocks of the epipolar gate's kernels (epipolar_blocks,
epipolar_kernel): the compile options (fast-math flags that keep NaN and inf, float32 1/sqrt
as the hardware estimate), raw pointer access to a detection's points, prefetch hints and
per-kernel LLVM function attributes. Imported only when numba is installed."""

from __future__ import annotations

import numba as nb
from numba.core import cgutils

from maem_ros.core.jit import NjitOptions

# no nnan/ninf fast-math flags: NaN (missing point) and inf (point at the epipole) must
# survive; error_model numpy removes the ZeroDivisionError branch that blocks SIMD;
# reassoc lets the sums vectorise
_FLAGS = {"reassoc", "contract", "arcp", "nsz"}
_OPTS: NjitOptions = dict(cache=True, error_model="numpy", boundscheck=False, nogil=True)
jit = nb.njit(fastmath=_FLAGS, **_OPTS)
# afn: float32 1/sqrt as the hardware estimate (_ESTIMATE; bounded by RSQRT_ERR)
jit32 = nb.njit(fastmath=_FLAGS | {"afn"}, **_OPTS)
plain = nb.njit(**_OPTS)
# per pair and block helpers: inlined, so the hot loop passes no array views through calls
inline = nb.njit(inline="always", **_OPTS)
inline32 = nb.njit(fastmath=_FLAGS | {"afn"}, inline="always", **_OPTS)


@nb.extending.intrinsic
def pointer_like(typingctx, like, address):
    """The int64 address as a pointer to like's dtype."""
    sig = nb.types.CPointer(like.dtype)(like, address)

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[1], context.get_value_type(signature.return_type))

    return sig, codegen


def _prefetch_intrinsic(locality: int, towards: str):
    """An intrinsic asking the CPU to bring the cache line at an int64 address towards
    ``towards`` (a hint: never faults, even for an address outside any mapping); LLVM's
    temporal locality 3 = L1, 2 = L2."""

    @nb.extending.intrinsic
    def intrinsic(typingctx, address):
        sig = nb.types.void(nb.types.int64)

        def codegen(context, builder, signature, args):
            # numba's codegen types (llvmlite, which numba brings): no import of llvmlite here
            byte_ptr = cgutils.voidptr_t
            i32 = cgutils.int32_t
            fn = builder.module.declare_intrinsic(
                "llvm.prefetch",
                [byte_ptr],
                cgutils.ir.FunctionType(cgutils.ir.VoidType(), [byte_ptr, i32, i32, i32]),
            )
            # read (0), locality, data cache (1)
            builder.call(fn, [builder.inttoptr(args[0], byte_ptr), i32(0), i32(locality), i32(1)])
            return context.get_dummy_value()

        return sig, codegen

    intrinsic.__doc__ = f"Prefetch the cache line at the int64 address towards {towards}."
    return intrinsic


prefetch = _prefetch_intrinsic(3, "L1")
prefetch_l2 = _prefetch_intrinsic(2, "L2")


#: LLVM function attribute: vectorise with 512-bit registers where the CPU has them. LLVM's
#: tuning for Intel server cores (and some others) caps vectors at 256 bits to avoid the clock
#: penalty of early AVX-512 parts; these float32 loops are compute-bound, and 512-bit vectors
#: made the epipolar stage of maem-bench --load large ~20 % faster (39 against 48 ms in
#: alternating runs on a 2-core Xeon VM), while the same setting process-wide
#: (NUMBA_CPU_FEATURES) slowed the float64 triangulation kernel by ~15 %: so per function
_WIDE = '"prefer-vector-width"="512"'


#: LLVM function attribute: a float32 1/sqrt (``afn``) is the hardware estimate alone, no
#: Newton step. x86's estimates are documented within 1.5 * 2^-12 relative (rsqrtps; the
#: AVX-512 rsqrt14ps that 512-bit loops take, 2^-14), inside epipolar.RSQRT_ERR = 2^-10, so
#: the error bound covers them (and rsqrt_check.rsqrt_within_bound checks it at first use). A
#: Newton step is 4 vector operations, twice per point of ~36: without it (and with
#: refined_pair's second try for the pairs the wider bound cannot settle) the large load's
#: three kernel levels took 20.1-20.4 -> 18.2-19.3 ms (alternating runs, 2-core Xeon VM).
#: Only on x86-64: other targets' estimates are coarser (AArch64's frsqrte: 8 bits), so they
#: keep LLVM's Newton steps
_ESTIMATE = '"reciprocal-estimates"="sqrtf:0,vec-sqrtf:0"'


def _function_attribute(attribute: str, doc: str, x86_only: bool = False):
    """An intrinsic that marks the calling kernel with the LLVM function attribute
    ``attribute`` (x86_only: on x86-64 targets only). A no-op where llvmlite's function
    attributes are not the set of printed strings they are today."""

    @nb.extending.intrinsic
    def intrinsic(typingctx):
        def codegen(context, builder, signature, args):
            attributes = builder.function.attributes
            x86 = builder.module.triple.startswith(("x86_64", "amd64"))
            if isinstance(attributes, set) and (x86 or not x86_only):
                # set.add: llvmlite's own add() accepts only LLVM's keyword attributes
                set.add(attributes, attribute)
            return context.get_dummy_value()

        return nb.types.none(), codegen

    intrinsic.__doc__ = doc
    return intrinsic


wide_vectors = _function_attribute(_WIDE, "Mark the calling kernel with _WIDE (else only narrower vectors).")
estimated_rsqrt = _function_attribute(
    _ESTIMATE, "Mark the calling float32 kernel with _ESTIMATE (x86-64 only).", x86_only=True
)


@inline
def points(like, address, start, count):
    """count coordinates from element start of the detection at address: a view without
    reference counting (a typed list of the cameras' arrays costs ~20 ns per access in the
    hot loop); the caller keeps the arrays alive."""
    return nb.carray(pointer_like(like, address + start * like.itemsize), (count,))

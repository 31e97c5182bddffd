"""One thread's scratch memory for the compiled match: the kernels take their working arrays from
it instead of allocating each (a call works with about a hundred arrays, and allocating
them would take a good part of a small track's call).

A bump allocator: :func:`reset` at the start of a call, then each ``take_*`` hands out the next
free piece of a buffer. Nothing is freed within a call, so pieces never overlap; a call's
pieces are overwritten by the next call of the same thread, so they must not outlive it (the
answer is copied out by :func:`mapmatch.batch.packed.pack`). When a buffer is used up the piece
is allocated on its own instead, and ``top`` still counts it, so the caller can grow the arena
(:meth:`Arena.grown`) for the next call.

Also two ways around numba's
reference counting: :func:`borrowed` views, and :data:`UNCOUNTED` kernels; and :func:`ref`,
a tuple of arrays handed to a compiled call by one pointer instead of by value.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple, cast

import numpy as np
from numba.core import cgutils, errors, types
from numba.core.datamodel import models
from numba.core.imputils import impl_ret_borrowed
from numba.extending import intrinsic, register_model
from numpy.typing import NDArray

from graph.jit import interpreted, njit

MAX_ITEMS = 1 << 22
"""An arena grows to at most this many items per buffer (32 MB of floats); a call needing more
allocates the rest (only memory and speed depend on it, never a result)."""


PAGE_BYTES = 4096
"""A memory page: a grown arena writes one byte in each page its first call will use."""

UNCOUNTED: dict[str, Any] = {"cache": True, "nogil": True, "_nrt": False}
"""``njit`` options of a kernel compiled without numba's reference counting (``_nrt``, the
option numba's own string kernels use). Otherwise numba makes a call for every array the kernel
is handed or copies, and a tuple of arrays passed on, or a function inlined into the kernel,
copies every array in it. Only for a kernel that allocates nothing (numba refuses to compile
one that does) and returns no array; its caller holds every array it reads."""

int64: Callable[[int], int] = np.int64  # type: ignore[assignment]
"""``np.int64``, typed for mypy as returning an ``int``. In a kernel, ``int64(0)`` is an int64
where a plain ``0`` is the literal 0: a kernel handed a literal (directly, or through a variable
that starts as one, as ``t = 1`` before a loop) is compiled once more for that value, a copy
no call uses, which only adds to the compile time."""


class Arena(NamedTuple):
    """Scratch buffers by dtype and the next free place in each (``top``: floats, integers, flags)."""

    f8: NDArray[np.float64]
    i8: NDArray[np.int64]
    b1: NDArray[np.bool_]
    top: NDArray[np.int64]

    @classmethod
    def new(cls, items: int = 0) -> Arena:
        """An arena of ``items`` items per buffer (0: every piece is allocated)."""
        return cls(
            np.empty(items),
            np.empty(items, dtype=np.int64),
            np.empty(items, dtype=np.bool_),
            np.zeros(3, np.int64),
        )

    def grown(self) -> Arena | None:
        """A larger arena when the last call needed more than this one holds, else None.

        The part of each buffer the last call used is mapped in here, one write a page: a new
        buffer's pages are otherwise mapped on first write, inside the next call, which then
        takes several times as long as the calls after it. The same pages are mapped, only
        earlier: at the end of the call that grew the arena, which takes longer by about that
        much."""
        used = self.top.tolist()
        need = max(used)
        if need <= len(self.f8) or len(self.f8) >= MAX_ITEMS:
            return None
        big = Arena.new(min(max(2 * need, 4096), MAX_ITEMS))
        for buf, n in zip((big.f8, big.i8, big.b1), used, strict=True):
            buf[:n].view(np.uint8)[::PAGE_BYTES] = 0
        return big


@njit(cache=True, nogil=True, inline="always")
def reset(ar):  # type: ignore[no-untyped-def]
    """Every buffer free again (the start of a call)."""
    ar.top[0] = 0
    ar.top[1] = 0
    ar.top[2] = 0


@njit(cache=True, nogil=True, inline="always")
def take_f8(ar, n):  # type: ignore[no-untyped-def]
    """``n`` floats (contents undefined, as ``np.empty``)."""
    p = ar.top[0]
    ar.top[0] = p + n
    if p + n <= len(ar.f8):
        return ar.f8[p : p + n]
    return np.empty(n)


@njit(cache=True, nogil=True, inline="always")
def take_xy(ar, n):  # type: ignore[no-untyped-def]
    """``(n, 2)`` floats (contents undefined)."""
    return take_f8(ar, 2 * n).reshape((n, 2))


@njit(cache=True, nogil=True, inline="always")
def take_i8(ar, n):  # type: ignore[no-untyped-def]
    """``n`` int64 (contents undefined)."""
    p = ar.top[1]
    ar.top[1] = p + n
    if p + n <= len(ar.i8):
        return ar.i8[p : p + n]
    return np.empty(n, dtype=np.int64)


@njit(cache=True, nogil=True, inline="always")
def take_b1(ar, n):  # type: ignore[no-untyped-def]
    """``n`` flags (contents undefined)."""
    p = ar.top[2]
    ar.top[2] = p + n
    if p + n <= len(ar.b1):
        return ar.b1[p : p + n]
    return np.empty(n, dtype=np.bool_)


@njit(cache=True, nogil=True, inline="always")
def full_f8(ar, n, v):  # type: ignore[no-untyped-def]
    """``n`` floats set to ``v``."""
    a = take_f8(ar, n)
    a[:] = v
    return a


@njit(cache=True, nogil=True, inline="always")
def full_i8(ar, n, v):  # type: ignore[no-untyped-def]
    """``n`` int64 set to ``v``."""
    a = take_i8(ar, n)
    a[:] = v
    return a


@njit(cache=True, nogil=True, inline="always")
def full_b1(ar, n, v):  # type: ignore[no-untyped-def]
    """``n`` flags set to ``v``."""
    a = take_b1(ar, n)
    a[:] = v
    return a


def _borrowed_value(context: Any, builder: Any, ty: Any, val: Any) -> Any:
    """``val`` of type ``ty`` with every array's owner (meminfo, parent) cleared."""
    if isinstance(ty, types.Array):
        ary = context.make_array(ty)(context, builder, value=val)
        ary.meminfo = cgutils.get_null_value(ary.meminfo.type)
        ary.parent = cgutils.get_null_value(ary.parent.type)
        return ary._getvalue()
    if isinstance(ty, types.BaseTuple):
        out = val
        for i, t in enumerate(cast(Any, ty)):
            item = _borrowed_value(context, builder, t, builder.extract_value(val, i))
            out = builder.insert_value(out, item, i)
        return out
    return val


def _borrowable(ty: Any) -> bool:
    if isinstance(ty, types.Array | types.Number | types.Boolean | types.NoneType):
        return True
    return isinstance(ty, types.BaseTuple) and all(_borrowable(t) for t in cast(Any, ty))


def _borrowed(typingctx: Any, x: Any) -> Any:
    """``x`` (an array, or a tuple or named tuple of arrays and numbers, nested) with views of
    its arrays that own nothing, like :func:`numba.carray`'s: no reference counting (numba's
    atomic increments and decrements were half the time of a small track's match).

    Only for arrays that outlive every use of the views: those the caller of the compiled
    call holds (the track's, a :class:`~mapmatch.batch.context.Context`'s) and pieces of
    them, within one call. A view must never be returned to Python or stored beyond it.
    """
    if not _borrowable(x):
        raise errors.TypingError(f"borrowed: {x} holds more than arrays and numbers")

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        return _borrowed_value(context, builder, sig.args[0], args[0])

    return x(x), codegen


borrowed: Any = intrinsic(prefer_literal=False)(_borrowed)
"""See :func:`_borrowed` (an intrinsic: called from compiled code only)."""


class Ref(types.Type):
    """numba's type of :func:`ref`: a pointer to a value of type ``of`` in a compiled caller's frame."""

    def __init__(self, of: Any) -> None:
        self.of = of
        super().__init__(name=f"Ref({of})")

    @property
    def key(self) -> Any:
        return self.of


@register_model(Ref)
class _RefModel(models.PrimitiveModel):  # type: ignore[misc]
    def __init__(self, dmm: Any, fe_type: Ref) -> None:
        super().__init__(dmm, fe_type, dmm.lookup(fe_type.of).get_value_type().as_pointer())


def _ref(typingctx: Any, x: Any) -> Any:
    """A pointer to a copy of ``x`` in the calling kernel's frame, for :func:`deref` in a kernel
    it calls: one word passed instead of the value.

    numba passes a tuple by value, every array in it as seven words: a call with a few dozen
    arrays copies over a kilobyte of stack per call (the Viterbi step's, once or twice a fix).
    How long that copy takes depends on where the compile happens to put the two copies in the
    frame: 4 KB apart, each load waits on the store before it (4K aliasing), which can make
    the whole match take twice as long. Made once, before a loop of calls, the
    copy is made once. The pointer is valid until the kernel that made it returns: only for
    the kernels it calls, never returned or stored. So ``ref`` must be called in that kernel,
    or in a function compiled into it (``inline="always"``, as
    :func:`mapmatch.batch.step.step_inputs`): called in a function of its own, it would
    point into that function's finished frame."""

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        return cgutils.alloca_once_value(builder, args[0])

    return Ref(x)(x), codegen


def _deref(typingctx: Any, r: Any) -> Any:
    """The value a :func:`ref` points to."""
    if not isinstance(r, Ref):
        raise errors.TypingError(f"deref: {r} is not a Ref")

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        return impl_ret_borrowed(context, builder, sig.return_type, builder.load(args[0]))

    return r.of(r), codegen


ref: Any = intrinsic(prefer_literal=False)(_ref)
"""See :func:`_ref` (an intrinsic: called from compiled code only)."""
deref: Any = intrinsic(prefer_literal=False)(_deref)
"""See :func:`_deref` (an intrinsic: called from compiled code only)."""


def _same(x: Any) -> Any:
    """The Python stand-in of :func:`borrowed`, :func:`ref` and :func:`deref`: ``x`` itself."""
    return x


if interpreted():  # kernels run as Python: no reference counts, no frames to point into
    borrowed = ref = deref = _same

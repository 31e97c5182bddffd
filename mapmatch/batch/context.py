"""What the compiled match reads besides the track, handed over as one pointer.

numba unboxes every array argument on every call (about 0.1 µs each, and a reference count
taken and dropped); the batch call read some 45 arrays and 35 numbers (the map's, one thread's
scratch and a config's parameters). A :class:`Context` holds them all in one numba structref,
built once per thread and config (:func:`new_context`, compiled and cached on disk like every
kernel), so a call passes the track's arrays and one pointer.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from numba import types
from numba.experimental import structref

from graph.jit import interpreted, njit

CONTEXT_FIELDS = ("q", "r", "p", "geom", "roads", "router", "grid", "gsc", "ar")
"""The fields of a :class:`Context`: the query, rule and kernel parameters
(:class:`~mapmatch.batch.run.QueryParams`, :class:`~mapmatch.batch.run.RuleParams`,
:class:`~mapmatch.batch.arrays.KernelParams`), the map's edge geometry, road arrays, route
queries (:class:`~mapmatch.routing.Router`, with the thread's workspace) and grid, then the
thread's grid marks and arena."""


@structref.register
class ContextType(types.StructRef):
    """The numba type of a :class:`Context`."""

    def preprocess_fields(self, fields: Any) -> tuple[tuple[str, Any], ...]:
        return tuple((name, types.unliteral(typ)) for name, typ in fields)


class Context(structref.StructRefProxy):
    """One thread's and one config's inputs of :func:`mapmatch.batch.run.run_track_in`
    (fields :data:`CONTEXT_FIELDS`; read only by compiled code). Build with :func:`new_context`:
    the proxy's own constructor compiles in every process."""


structref.define_constructor(Context, ContextType, list(CONTEXT_FIELDS))
structref.define_boxing(ContextType, Context)


class PlainContext(NamedTuple):
    """A :class:`Context`'s stand-in when kernels run as Python (a structref has no Python
    implementation): the same fields (:data:`CONTEXT_FIELDS`)."""

    q: Any
    r: Any
    p: Any
    geom: Any
    roads: Any
    router: Any
    grid: Any
    gsc: Any
    ar: Any


_new: Any = PlainContext if interpreted() else Context
"""What :func:`new_context` builds: a :class:`Context`, or with kernels run as Python a
:class:`PlainContext`."""


@njit(cache=True)
def new_context(mi):  # type: ignore[no-untyped-def]
    """A :class:`Context` (:class:`PlainContext` when kernels run as Python) of a
    :class:`~mapmatch.batch.run.MatchInputs`'s fields (see :data:`CONTEXT_FIELDS`)."""
    return _new(mi.q, mi.r, mi.p, mi.geom, mi.roads, mi.router, mi.grid, mi.gsc, mi.ar)

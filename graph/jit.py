"""Compiled kernels: numba's ``njit`` with on-disk caches kept in step with the sources, and the
helpers every kernel module shares.

Every module that defines a kernel takes :func:`njit` from here. Its first use in a process
runs :func:`graph.kernel_cache.refresh_installed`, before any kernel is defined and so before any
cached kernel loads; importing a package compiles or checks nothing.
"""

from __future__ import annotations

import ast
import inspect
import textwrap
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from graph.kernel_cache import refresh_installed

PYTHON_MAX_ITEMS = 50_000
"""Inputs of up to this many items run a kernel as plain Python (:func:`for_size`); about
0.2 s at that size, against 1-3 s to compile each kernel."""

_refreshed = False


def njit(*args: Any, **options: Any) -> Any:
    """``numba.njit``, after the caches of changed sources are cleared (once per process).

    When kernels run interpreted (:func:`interpreted`), the function as numba would compute it
    (:func:`as_compiled`); its ``py_func`` is the function itself."""
    global _refreshed
    if not _refreshed:
        _refreshed = True
        refresh_installed()
    if interpreted():
        if len(args) == 1 and callable(args[0]) and not options:
            return as_compiled(args[0])
        return as_compiled
    return numba.njit(*args, **options)


def jitable(func: Callable[..., Any]) -> Callable[..., Any]:
    """``numba.extending.register_jitable``: ``func`` callable from plain Python (as it is) and
    from kernels (compiled into them). When kernels run interpreted, kernels call its
    :func:`as_compiled` copy and Python callers the function itself, as when compiled."""
    _JITABLE[func.__name__] = func
    if interpreted():
        return func
    from numba.extending import register_jitable

    return register_jitable(func)  # type: ignore[no-any-return]


_JITABLE: dict[str, Callable[..., Any]] = {}
"""The :func:`jitable` functions by name (their :func:`as_compiled` copies are what interpreted
kernels call)."""


def int_power(v: Any, n: int) -> Any:
    """``v ** n`` for a constant whole ``n`` as a kernel computes it: by repeated
    multiplication (numba unrolls the loop of ``static_power_impl``), where Python calls the
    C library's ``pow``, which can differ in the last bit."""
    res = type(v)(1)
    val = v
    e = abs(n)
    while e:
        if e & 1:
            res = res * val
        e >>= 1
        val = val * val
    return 1.0 / res if n < 0 else res


class _AsCompiled(ast.NodeTransformer):
    """Rewrites a kernel's source as numba computes it: ``x ** <int>`` to :func:`int_power`,
    a call of a :func:`jitable` function to its compiled-as copy (``__jitable_NAME__``)."""

    def __init__(self) -> None:
        self.changed = False
        self.jitables: set[str] = set()

    def visit_BinOp(self, node: ast.BinOp) -> ast.AST:
        self.generic_visit(node)
        c = node.right
        if isinstance(node.op, ast.Pow) and isinstance(c, ast.Constant) and type(c.value) is int:
            self.changed = True
            call = ast.Call(ast.Name("__int_power__", ast.Load()), [node.left, c], [])
            return ast.copy_location(call, node)
        return node

    def visit_Name(self, node: ast.Name) -> ast.AST:
        if isinstance(node.ctx, ast.Load) and node.id in _JITABLE:
            self.changed = True
            self.jitables.add(node.id)
            return ast.copy_location(ast.Name(f"__jitable_{node.id}__", ast.Load()), node)
        return node


def as_compiled(func: Callable[..., Any]) -> Callable[..., Any]:
    """``func`` as numba computes it, to run interpreted: its source rewritten by
    :class:`_AsCompiled` (in its own module, so its globals are the module's), else ``func``
    itself when nothing needs rewriting. ``py_func`` of the result is ``func``."""
    try:
        source = textwrap.dedent(inspect.getsource(func))
        tree = ast.parse(source)
    except (OSError, TypeError, SyntaxError):
        return func
    fdef = tree.body[0]
    if not isinstance(fdef, ast.FunctionDef) or func.__code__.co_freevars:
        return func
    fdef.decorator_list = []
    rewrite = _AsCompiled()
    tree = ast.fix_missing_locations(rewrite.visit(tree))
    if not rewrite.changed:
        return func
    ast.increment_lineno(tree, func.__code__.co_firstlineno - 1)
    g = func.__globals__
    g["__int_power__"] = int_power
    for name in rewrite.jitables:
        if f"__jitable_{name}__" not in g:
            g[f"__jitable_{name}__"] = as_compiled(_JITABLE[name])
    ns: dict[str, Any] = {}
    exec(compile(tree, inspect.getsourcefile(func) or "<kernel>", "exec"), g, ns)
    out: Any = ns[fdef.name]
    out.__defaults__, out.__kwdefaults__ = func.__defaults__, func.__kwdefaults__
    out.__qualname__, out.__doc__ = func.__qualname__, func.__doc__
    out.py_func = func
    return out  # type: ignore[no-any-return]


def kernels_called(funcs: Iterable[Any]) -> list[Any]:
    """The numba dispatchers among ``funcs`` and every dispatcher they call, directly or through
    :func:`jitable` functions, found by name in their modules' globals; each once."""
    from numba.core.dispatcher import Dispatcher

    seen: dict[int, Any] = {}
    todo = list(funcs)
    while todo:
        f = todo.pop()
        if id(f) in seen:
            continue
        seen[id(f)] = f
        py = getattr(f, "py_func", f)
        code, glob = getattr(py, "__code__", None), getattr(py, "__globals__", {})
        codes = [code] if code is not None else []
        while codes:
            c = codes.pop()
            codes += [k for k in c.co_consts if isinstance(k, type(c))]
            for name in c.co_names:
                v = glob.get(name)
                if isinstance(v, Dispatcher) or (v is not None and _JITABLE.get(name) is v):
                    todo.append(v)
    return [f for f in seen.values() if isinstance(f, Dispatcher)]


class _Tier(threading.local):
    compiled = False


_TIER = _Tier()
"""Per thread: whether a tiered kernel's call from Python runs compiled (:func:`compiled_calls`)."""
_TIERED_CLASSES: dict[type, type] = {}


def _tiered_class(base: type) -> type:
    """A subclass of the dispatcher class ``base`` whose call from Python runs the kernel's
    :func:`as_compiled` twin, or (in a :func:`compiled_calls` block) the compiled kernel. Its
    instances are still ``base`` dispatchers to numba: compiled callers call them compiled."""
    cls = _TIERED_CLASSES.get(base)
    if cls is None:
        call = base.__call__  # type: ignore[operator]

        def __call__(self: Any, *args: Any, **kwargs: Any) -> Any:
            if _TIER.compiled:
                return call(self, *args, **kwargs)
            twin = self.__dict__.get("_mapmatch_twin")
            if twin is None:
                twin = self.__dict__["_mapmatch_twin"] = as_compiled(self.py_func)
            return twin(*args, **kwargs)

        cls = type(f"Tiered{base.__name__}", (base,), {"__call__": __call__, "__slots__": ()})
        _TIERED_CLASSES[base] = cls
    return cls


def tier(kernels: Iterable[Any]) -> list[Any]:
    """Run ``kernels`` (numba dispatchers) and every kernel they call interpreted when called
    from Python, while they compile elsewhere: each is given a dispatcher class whose call from
    Python runs its :func:`as_compiled` twin (the same answers, nothing compiled in this
    process), whose own calls of kernels go to their twins in turn. Returns the kernels tiered,
    for :func:`untier`. Compiled code calling them is unchanged."""
    out = []
    for d in kernels_called(kernels):
        base = type(d)
        if base in _TIERED_CLASSES.values():
            continue
        d.__class__ = _tiered_class(base)
        out.append(d)
    return out


def untier(kernels: Iterable[Any]) -> None:
    """Undo :func:`tier`: the kernels' calls from Python run compiled again (the plain
    dispatcher class: no cost per call)."""
    for d in kernels:
        base = type(d).__mro__[1]
        if type(d) is _TIERED_CLASSES.get(base):
            d.__class__ = base


@contextmanager
def compiled_calls() -> Iterator[None]:
    """In this block, this thread's calls of tiered kernels (:func:`tier`) run compiled: they
    load from numba's cache or compile, while other threads keep running the twins."""
    was = _TIER.compiled
    _TIER.compiled = True
    try:
        yield
    finally:
        _TIER.compiled = was


def read_only(a: Any, dtype: Any) -> NDArray[Any]:
    """``a`` as a C-contiguous array of ``dtype`` that kernels cannot write: a read-only view.

    A map read from its file has read-only arrays, one built in memory writable ones, and numba
    compiles a kernel once per argument type, writability included: every array a kernel only
    reads goes in read-only, whatever its source, so one compile serves both."""
    v = np.ascontiguousarray(a, dtype=dtype).view()
    v.flags.writeable = False
    return v


def interpreted() -> bool:
    """Whether kernels run as plain Python in this process (``NUMBA_DISABLE_JIT``, set by
    :func:`mapmatch.kernels.set_mode` before the first kernel is defined): ``njit`` then
    returns each function as numba computes it (:func:`as_compiled`), and the few numba-only
    constructs take their Python stand-ins."""
    return bool(numba.config.DISABLE_JIT)  # type: ignore[attr-defined]


def py_func(kernel: Any) -> Callable[..., Any]:
    """The Python function of ``kernel``: a dispatcher's ``py_func``, or ``kernel`` itself when
    kernels run interpreted (``NUMBA_DISABLE_JIT``: ``njit`` then returns the function)."""
    return getattr(kernel, "py_func", kernel)  # type: ignore[no-any-return]


def for_size(kernel: Any, items: int) -> Callable[..., Any]:
    """``kernel`` (a numba dispatcher) for an input of ``items`` items: its Python function when
    the input is small (no compile; the same code, so the same results), else the compiled kernel.

    Only for kernels that call no other compiled function (those would compile anyway).
    """
    return py_func(kernel) if items <= PYTHON_MAX_ITEMS else kernel  # type: ignore[no-any-return]

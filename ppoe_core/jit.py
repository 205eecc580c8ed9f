"""``njit`` for kernels that a process may never need to compile: numba is imported, and the dispatcher made, on
the first call, and an ahead-of-time compiled function (:mod:`ppoe_core.aot`) may stand in for it.

``import numba`` costs about 60 MB of memory and a second of start-up, and loading a cached kernel about 40 MB more
(numba's typing and lowering registries, LLVM); a module whose kernels are declared with this ``njit`` imports
without numba.  The kinematics node's whole path (:mod:`ppoe_core.model.chain_kernel`,
:mod:`ppoe_core.model.joint_history`, :mod:`ppoe_core.io.joint_pose`, :mod:`ppoe_core.lie.kernels`) is declared so,
which is what lets it run on the ahead-of-time module alone, without numba (docs/performance.md, "Memory").

How it works:

* ``@njit(...)`` (same options as :func:`numba.njit`) returns a :class:`Kernel` and records it under its module;
* the first call of any kernel of a module *binds* the module (:func:`bind`): each kernel gets its numba dispatcher
  (``numba.njit(**options)(py_func)``: cache, inlining and specialisation exactly as with the decorator), and every
  module global that is a :class:`Kernel` (its own, or one imported from another module) is replaced by the
  dispatcher, so numba sees dispatchers when it compiles a caller and Python callers in the module call the
  dispatcher directly from then on;
* with :func:`use_ahead_of_time` (the kinematics node), a kernel that the ahead-of-time module exports is bound to
  the compiled function instead (no numba at all); a kernel that it lacks switches its module and the modules it
  calls into back to numba (:func:`bind` with ``jit=True``), with one log line naming the kernel.

A reference kept by another module (``from m import kernel``) stays the :class:`Kernel` object: its call forwards
to the current binding (one Python call more; cache :func:`bound` where it matters).
"""

from __future__ import annotations

import functools
import logging
import sys
import threading
from collections.abc import Callable
from typing import Any

__all__ = ["Kernel", "njit", "bind", "bound", "use_ahead_of_time", "ahead_of_time_in_use", "kernels_of"]

LOG = logging.getLogger(__name__)

#: module name -> its kernels, in definition order
_KERNELS: dict[str, list[Kernel]] = {}
#: module name -> "aot" or "jit": how its globals are bound now
_BOUND: dict[str, str] = {}
#: the ahead-of-time functions in use: kernel key "module.name" -> callable (set by use_ahead_of_time)
_AOT: dict[str, Callable[..., Any]] = {}
#: modules being bound now (a module holding kernels of a module that holds kernels of it)
_BINDING: set[str] = set()
#: held while a module is bound: another thread's first call of one of its kernels waits for the binding to end
#: (it read ``_BINDING`` and went on before ``_BOUND`` was set: a KeyError in evaluate's tag threads); re-entrant,
#: because binding a module binds the modules whose kernels it holds, in the same thread
_BIND_LOCK = threading.RLock()
#: set once the compile log is attached to numba
_WATCHING: list[bool] = []
#: module name -> {global name: Kernel} as first seen (the globals are then replaced by their bindings)
_HELD: dict[str, dict[str, Kernel]] = {}


class Kernel:
    """A kernel declared with :func:`njit`; see the module docstring.

    Attributes
    ----------
    py_func : function
        The Python function (as numba's dispatcher's ``py_func``).
    options : dict
        Options for :func:`numba.njit`.
    """

    def __init__(self, py_func: Callable[..., Any], options: dict[str, Any]) -> None:
        functools.update_wrapper(self, py_func)
        self.py_func = py_func
        self.options = options
        self.key = f"{py_func.__module__}.{py_func.__name__}"
        self._jit: Any = None
        _KERNELS.setdefault(py_func.__module__, []).append(self)

    def __call__(self, *args: Any) -> Any:
        return bound(self)(*args)

    def __getattr__(self, name: str) -> Any:
        # dispatcher attributes (signatures, py_func of numba's, inspect_* ...): the numba dispatcher
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self.jit(), name)

    def jit(self) -> Any:
        """The numba dispatcher of this kernel (its module bound to numba first)."""
        if self._jit is None:
            bind(self.py_func.__module__, jit=True)
            if self._jit is None:  # being bound right now (a cycle): make it here
                import numba

                self._jit = numba.njit(**self.options)(self.py_func)
        return self._jit

    def __repr__(self) -> str:
        return f"<Kernel {self.key}>"


def njit(*args: Any, **options: Any) -> Any:
    """Drop-in for :func:`numba.njit` (bare or with options) that defers numba to the first call."""
    if args and callable(args[0]) and len(args) == 1 and not options:
        return Kernel(args[0], {})

    def decorate(func: Callable[..., Any]) -> Kernel:
        return Kernel(func, dict(options))

    return decorate


def kernels_of(module: str) -> list[Kernel]:
    """The kernels declared in ``module`` (definition order)."""
    return list(_KERNELS.get(module, []))


def bound(kernel: Any) -> Callable[..., Any]:
    """What a call of ``kernel`` runs now (binding its module on first use): the ahead-of-time function or the
    numba dispatcher; anything that is not a :class:`Kernel` is returned as it is."""
    if not isinstance(kernel, Kernel):
        return kernel
    module = kernel.py_func.__module__
    if module not in _BOUND:
        bind(module)
    if _BOUND.get(module) == "aot" and kernel.key in _AOT:
        return _AOT[kernel.key]
    return kernel.jit()


def bind(module: str, jit: bool = False) -> None:
    """Bind the kernels held by ``module`` (module docstring): to the ahead-of-time functions where there are some
    and ``jit`` is False (the others stay :class:`Kernel` objects until called), else to numba dispatchers (the
    modules whose kernels it holds first)."""
    with _BIND_LOCK:
        held = _held(module)
        aot = not jit and any(k.key in _AOT for k in held.values())
        mode = "aot" if aot else "jit"
        if module in _BINDING or _BOUND.get(module) == mode or _BOUND.get(module) == "jit":
            return
        _BINDING.add(module)
        try:
            _bind(module, aot)
        finally:
            _BINDING.discard(module)


def _held(module: str) -> dict[str, Kernel]:
    """The module globals that are kernels (its own and imported ones), as first seen (later replaced by what they
    are bound to)."""
    held = _HELD.get(module)
    if held is None:
        held = _HELD[module] = {n: v for n, v in vars(sys.modules[module]).items() if isinstance(v, Kernel)}
    return held


def _bind(module: str, aot: bool) -> None:
    mod = sys.modules[module]
    held = _held(module)
    _BOUND[module] = "aot" if aot else "jit"
    if aot:
        for name, k in held.items():
            setattr(mod, name, _AOT.get(k.key, k))
        return
    import numba

    _watch_compiles()
    if _AOT:
        LOG.info("ahead-of-time kernels: %s is bound to numba (a kernel of it is not in the module)", module)
    for k in held.values():  # the kernels it calls, from other modules: numba dispatchers first
        if k.py_func.__module__ != module:
            bind(k.py_func.__module__, jit=True)
    for k in _KERNELS.get(module, []):
        if k._jit is None:
            k._jit = numba.njit(**k.options)(k.py_func)
    for name, k in held.items():
        setattr(mod, name, k.jit())


def _watch_compiles() -> None:
    """Log each kernel numba compiles because its cache lacks it (once numba is loaded; once per process)."""
    if _WATCHING:
        return
    _WATCHING.append(True)
    from numba.core import event

    class _Named(event.Listener):
        def __init__(self) -> None:
            self.depth = 0

        def on_start(self, ev: Any) -> None:
            self.depth += 1
            if self.depth == 1:
                func = getattr(ev.data.get("dispatcher"), "py_func", None)
                name = f"{getattr(func, '__module__', '?')}.{getattr(func, '__qualname__', '?')}"
                LOG.info("compiling %s: not in numba's cache (first use of this install or cache directory; "
                         "'ppoe warmup' compiles every node's kernels beforehand)", name)

        def on_end(self, ev: Any) -> None:
            self.depth -= 1

    event.register("numba:compile", _Named())


def use_ahead_of_time(functions: dict[str, Callable[..., Any]]) -> None:
    """Use these ahead-of-time compiled functions (kernel key ``"module.name"`` -> function) for the kernels of
    modules not bound yet (:mod:`ppoe_core.aot` loads them)."""
    _AOT.update(functions)


def ahead_of_time_in_use() -> bool:
    """True when ahead-of-time functions were given and numba has not been imported."""
    return bool(_AOT) and "numba" not in sys.modules

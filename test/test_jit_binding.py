"""ppoe_core.jit: a kernel's first call from a second thread while its module is being bound by the first.

``ppoe evaluate`` detects tags in threads; the first call of a kernel in one thread binds the kernel's module (numba
dispatchers replace the module's kernels), and a call of the same module's kernel from another thread during that
binding used to read the half-bound state and raise ``KeyError: '<module>'``."""

from __future__ import annotations

import sys
import threading
import time
import types
from typing import Any

import pytest

from ppoe_core import jit

#: how long the first thread's binding is held open, so that the second thread's call lands inside it [s]
HOLD_S = 0.5


def _module_with_a_kernel(name: str) -> types.ModuleType:
    mod = types.ModuleType(name)
    sys.modules[name] = mod
    source = "from ppoe_core.jit import njit\n\n@njit(cache=False)\ndef twice(x):\n    return 2.0 * x\n"
    exec(compile(source, f"<{name}>", "exec"), mod.__dict__)
    return mod


def test_a_second_thread_waits_for_the_binding_instead_of_failing(monkeypatch: pytest.MonkeyPatch) -> None:
    name = "ppoe_test_jit_binding_race"
    mod = _module_with_a_kernel(name)
    kernel = mod.twice
    real_bind = jit._bind
    entered = threading.Event()

    def slow_bind(module: str, aot: bool) -> None:
        if module == name:
            entered.set()
            time.sleep(HOLD_S)  # the first thread is inside the binding (as when numba is imported for it)
        real_bind(module, aot)

    monkeypatch.setattr(jit, "_bind", slow_bind)
    results: dict[str, Any] = {}

    def call(tag: str) -> None:
        try:
            results[tag] = jit.bound(kernel)(3.0)
        except Exception as exc:  # noqa: BLE001 - the failure this test is about
            results[tag] = exc

    first = threading.Thread(target=call, args=("first",))
    first.start()
    assert entered.wait(30.0)
    second = threading.Thread(target=call, args=("second",))
    second.start()
    first.join(60.0)
    second.join(60.0)
    try:
        assert results == {"first": 6.0, "second": 6.0}, results
    finally:
        sys.modules.pop(name, None)

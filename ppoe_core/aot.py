"""Ahead-of-time compiled kernels of the kinematics node (numba's ``pycc``): the node runs without numba.

Why (docs/performance.md, "Memory"): a process that imports numba and loads one cached kernel holds about 175 MB
(rclpy 46 MB; ``import numba`` +62 MB, libLLVM's pages and numba's modules; the first cached kernel +65 MB, numba's
typing/lowering registries and the JIT), above the kinematics node's 150 MB target whatever the node does.  The same
kernels compiled ahead of time into one CPython extension (about 1 MB) load in a few milliseconds and a few MB, and
need neither numba nor LLVM at run time.

What: the kernels the kinematics node calls (:data:`KINEMATICS_KERNELS`), each exported for exactly the argument
types the node passes: :func:`build` first runs the node's own warm-up (:func:`ppoe_core.node_warmup.warm`) with
numba, reads the signatures numba compiled, and exports a wrapper per signature (the wrapper calls the kernel's own
dispatcher, so the kernel keeps its options: fused multiply-add, inlining).  Same source, same floats: one
implementation (``test/test_aot.py`` compares the node's bytes on a stream of messages both ways).

Where: beside numba's cache (:func:`ppoe_core.compile_cache.cache_location`): ``ppoe_core/__pycache__`` when the
package is writable, else the user/temp cache directory (``PPOE_AOT_DIR`` overrides it); a manifest (JSON) records
the source files' hash, the Python/numpy/numba versions and the CPU (the code uses the host's instruction set), and
:func:`load` refuses a module that does not match them (the node then uses numba and says why, once).

Trade (docs/performance.md): it needs a C compiler when it is built (``ppoe warmup``, the README's set-up command,
``colcon build``); it is built on the machine that runs it (host CPU), not shipped in wheels; numba marks ``pycc`` as
pending deprecation (its replacement is not released), so without ``pycc`` or a compiler everything still runs on
numba, at about 190 MB for the kinematics node.  AOT functions do not check their arguments' types: only the
audited call sites of the kernels below reach them (fixed dtypes and C-contiguous arrays made by the callers).
"""

from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import json
import logging
import os
import platform
import shutil
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from ppoe_core import jit
from ppoe_core.compile_cache import cache_location

__all__ = ["KINEMATICS_KERNELS", "AotStatus", "aot_dir", "build", "load", "loaded", "status"]

LOG = logging.getLogger(__name__)

#: the kernels of the kinematics node's path (module.function), exported for the signatures its warm-up compiles
KINEMATICS_KERNELS: tuple[str, ...] = (
    "ppoe_core.model.chain_kernel.fk_one",
    "ppoe_core.io.joint_pose.joint_state_pose",
    "ppoe_core.io.joint_pose.chain_pose_cdr",
    "ppoe_core.model.joint_history.merge_message",
    "ppoe_core.lie.kernels.quat_from_matrix_one",
    "ppoe_core.lie.kernels.rotate_covariance_one",
    "ppoe_core.lie.kernels.so3_exp_kernel",
    "ppoe_core.lie.kernels.covariance_passes_kernel",
)
#: name of the extension module and its manifest
MODULE_NAME = "ppoe_aot_kinematics"
MANIFEST_VERSION = 1
#: environment variable: ``0`` = do not use the ahead-of-time module (numba's cache instead)
ENV_SWITCH = "PPOE_AOT"
#: environment variable: the ahead-of-time module's directory instead of the one beside numba's cache (a test or a
#: benchmark builds its own module while the kernels keep the install's numba cache)
ENV_DIR = "PPOE_AOT_DIR"


class AotStatus(NamedTuple):
    """What :func:`status` found: ``usable`` and, if not, why (for the log line and ``ppoe warmup``)."""

    usable: bool
    why: str
    path: Path | None


def aot_dir() -> Path | None:
    """Directory of the ahead-of-time module: ``$PPOE_AOT_DIR`` when set, else ``ppoe_core/__pycache__`` for a
    writable package, else ``aot/`` in the kernel cache directory; None when caching is off."""
    if os.environ.get(ENV_DIR):
        return Path(os.environ[ENV_DIR])
    loc = cache_location()
    if loc.directory is None:
        return None
    if loc.kind == "package":
        return Path(__file__).resolve().parent / "__pycache__"
    return Path(loc.directory) / "aot"


def _cpu_fingerprint() -> str:
    """The CPU model and instruction-set flags (the module is compiled for the host CPU)."""
    text = ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith(("model name", "flags", "Features", "CPU part")):
                    text += line.strip() + "\n"
                if line.strip() == "":
                    break
    except OSError:
        pass
    text += platform.machine() + platform.processor()
    return hashlib.sha1(text.encode()).hexdigest()


def _sources_hash(files: Sequence[str]) -> str:
    h = hashlib.sha1()
    for f in sorted(files):
        h.update(f.encode())
        h.update(Path(f).read_bytes())
    return h.hexdigest()


def _environment() -> dict[str, str]:
    import numpy

    return {"python": sys.version.split()[0], "numpy": numpy.__version__, "cpu": _cpu_fingerprint(),
            "platform": sys.platform}


def status() -> AotStatus:
    """Whether the module in :func:`aot_dir` matches this install (sources, versions, CPU)."""
    d = aot_dir()
    if d is None:
        return AotStatus(False, "no cache directory (caching is off)", None)
    manifest = d / f"{MODULE_NAME}.json"
    try:
        info = json.loads(manifest.read_text())
    except (OSError, ValueError):
        return AotStatus(False, f"not built ({manifest} missing: run 'ppoe warmup')", None)
    path = d / info.get("file", "")
    if info.get("version") != MANIFEST_VERSION or not path.is_file():
        return AotStatus(False, f"{manifest}: unknown format or module missing (run 'ppoe warmup')", None)
    env = _environment()
    changed = [k for k, v in env.items() if info.get("environment", {}).get(k) != v]
    if changed:
        return AotStatus(False, f"built for another {', '.join(changed)} (run 'ppoe warmup')", None)
    try:
        if _sources_hash(info["sources"]) != info["sources_hash"]:
            return AotStatus(False, "the kernels' sources changed since it was built (run 'ppoe warmup')", None)
    except (OSError, KeyError):
        return AotStatus(False, "a kernel source file moved since it was built (run 'ppoe warmup')", None)
    return AotStatus(True, "", path)


_LOADED: list[AotStatus] = []


def loaded() -> AotStatus | None:
    """What the last :func:`load` of this process found (None: not tried)."""
    return _LOADED[-1] if _LOADED else None


def load() -> AotStatus:
    """Load the module and hand its functions to :func:`ppoe_core.jit.use_ahead_of_time` (kernels bound from then
    on use them); returns the status (not usable: nothing changes, the kernels use numba)."""
    st = _load()
    _LOADED.append(st)
    return st


def _load() -> AotStatus:
    if os.environ.get(ENV_SWITCH, "1") == "0":
        return AotStatus(False, f"switched off ({ENV_SWITCH}=0)", None)
    st = status()
    if not st.usable or st.path is None:
        return st
    info = json.loads((st.path.parent / f"{MODULE_NAME}.json").read_text())
    loader = importlib.machinery.ExtensionFileLoader(MODULE_NAME, str(st.path))
    spec = importlib.util.spec_from_file_location(MODULE_NAME, st.path, loader=loader)
    if spec is None:
        return AotStatus(False, f"{st.path}: cannot be imported", None)
    try:
        mod = importlib.util.module_from_spec(spec)
        loader.exec_module(mod)
    except ImportError as exc:
        return AotStatus(False, f"{st.path}: {exc}", None)
    functions = {key: _chooser([(getattr(mod, v["symbol"]), v["none"]) for v in variants])
                 for key, variants in info["kernels"].items()}
    jit.use_ahead_of_time(functions)
    return st


def _chooser(variants: list[tuple[Callable[..., Any], list[int]]]) -> Callable[..., Any]:
    """One function per kernel: the only variant, or the one whose None arguments (``fourth`` of the FK kernels:
    order 2 or 4) are the call's."""
    if len(variants) == 1:
        return variants[0][0]
    positions = sorted({i for _, none in variants for i in none})
    table = {tuple(i in none for i in positions): f for f, none in variants}

    def choose(*args: Any) -> Any:
        return table[tuple(args[i] is None for i in positions)](*args)

    return choose


# ---------------------------------------------------------------------------------------------------------- build


def build(warm: Callable[[], None], directory: Path | None = None) -> Path:
    """Compile :data:`KINEMATICS_KERNELS` ahead of time into ``directory`` (default :func:`aot_dir`).

    ``warm`` runs the node's path with numba first (the signatures to export are the ones it compiled).  Needs
    numba's ``pycc`` and a C compiler.

    Raises
    ------
    RuntimeError
        Naming what is missing (pycc, a compiler, a kernel the warm-up did not compile).
    """
    import warnings

    directory = aot_dir() if directory is None else Path(directory)
    if directory is None:
        raise RuntimeError("no writable cache directory for the ahead-of-time module")
    warm()
    from numba.core import types

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numba's pending-deprecation notice of pycc
        try:
            from numba.pycc import CC
        except ImportError as exc:
            raise RuntimeError(f"numba.pycc is not available ({exc})") from None
    cc = CC(MODULE_NAME)
    cc.target_cpu = "host"
    cc.verbose = False
    manifest: dict[str, Any] = {}
    for key in KINEMATICS_KERNELS:
        manifest[key] = []
        dispatcher = _kernel(key).jit()
        if not dispatcher.signatures:
            raise RuntimeError(f"{key}: the warm-up did not compile it")
        for sig in dispatcher.signatures:
            symbol = f"k{sum(len(v) for v in manifest.values())}"
            ret = dispatcher.overloads[sig].signature.return_type
            cc.export(symbol, ret(*sig))(_wrapper(dispatcher, len(sig)))
            manifest[key].append({"symbol": symbol, "none": [i for i, t in enumerate(sig) if t == types.none]})
    sources = sorted({str(Path(sys.modules[m].__file__ or "").resolve()) for m in _kernel_modules()})
    with tempfile.TemporaryDirectory(prefix="ppoe-aot-") as tmp:
        cc.output_dir = tmp
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                cc.compile()
            except Exception as exc:  # noqa: BLE001 - distutils/compiler errors of any kind
                raise RuntimeError(f"compiling the ahead-of-time module failed (a C compiler is needed): "
                                   f"{type(exc).__name__}: {exc}") from None
        built = next(Path(tmp).glob(f"{MODULE_NAME}*"))
        directory.mkdir(parents=True, exist_ok=True)
        target = directory / built.name
        partial = directory / (built.name + ".partial")
        shutil.copyfile(built, partial)
        os.replace(partial, target)
    info = {"version": MANIFEST_VERSION, "file": target.name, "environment": _environment(),
            "sources": sources, "sources_hash": _sources_hash(sources), "kernels": manifest}
    partial = directory / f"{MODULE_NAME}.json.partial"
    partial.write_text(json.dumps(info, indent=1))
    os.replace(partial, directory / f"{MODULE_NAME}.json")
    return target


def _kernel(key: str) -> jit.Kernel:
    module, name = key.rsplit(".", 1)
    importlib.import_module(module)
    for k in jit.kernels_of(module):
        if k.py_func.__name__ == name:
            return k
    raise RuntimeError(f"{key} is not a ppoe_core.jit kernel")


def _kernel_modules() -> list[str]:
    """Modules whose source decides the exported code: those of every kernel bound so far (the warm-up's)."""
    return [m for m in sys.modules if jit.kernels_of(m) and m.startswith("ppoe_core")]


def _wrapper(dispatcher: Any, nargs: int) -> Callable[..., Any]:
    """``def w(a0, ..., a{n-1}): return kernel(a0, ..., a{n-1})`` calling ``dispatcher`` (keeps its options)."""
    names = ", ".join(f"a{i}" for i in range(nargs))
    namespace: dict[str, Any] = {"kernel": dispatcher}
    exec(f"def wrapper({names}):\n    return kernel({names})\n", namespace)  # noqa: S102 - fixed template
    return namespace["wrapper"]

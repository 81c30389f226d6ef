"""Ahead-of-time compiled pipeline kernels (private): no numba at start-up.

Importing numba and loading its ``cache=True`` code cost a new worker process
about 330 ms of CPU (numba's import, then LLVM to load the cached object
code); that was most of a cloud's cold start.  This module compiles the
public kernels of :mod:`scmr_mesh.imaging._srm_kernels` once, with
``numba.pycc``, into a plain C extension that needs only numpy, and hands out
those functions instead of the JIT dispatchers::

    python -m scmr_mesh.imaging._aot          # what `make` runs after install

builds ``__pycache__/_srm_aot.<key>.so`` (and ``.json``) beside the kernels,
with the argument types the pipeline's :func:`~scmr_mesh.imaging.pipeline.warm_up`
uses and code for this CPU.  ``<key>`` hashes the kernels' source, numpy's
version, the Python ABI and the CPU's flags, so a module built from older
kernels (or for another machine) is never loaded.

At run time ``from scmr_mesh.imaging._aot import srm_kernel`` gives the AOT
function when a module for the current key exists, else the numba dispatcher
(JIT, ``cache=True``), which is always correct.  An AOT function checks its
arguments against the types it was built for (pycc's own wrappers do not:
a wrong dtype crashes) and passes anything else to the JIT dispatcher.

``SCMR_AOT=0`` turns the AOT path off (the build itself runs that way).
:func:`status` says which path is in use and why.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import sys
import sysconfig
from pathlib import Path
from typing import Any, Callable

log = logging.getLogger(__name__)

#: The kernels called from outside ``_srm_kernels`` (srm.py, steps.py, road_model.py, codec.py).
KERNELS: tuple[str, ...] = ("srm_kernel", "b2_table", "remove_sparse_kernel", "column_fill_kernel",
                             "road_share_kernel", "candidate_kernel", "area_rows_kernel", "area_round_kernel",
                             "area_half_kernel", "boundary_sides_kernel", "boundary_cut_kernel",
                             "row_medians_kernel", "rough_rows_kernel")

#: Environment switch: ``0`` uses the numba JIT even when an AOT module exists.
ENV = "SCMR_AOT"

_HERE = Path(__file__).resolve().parent
SOURCE = _HERE / "_srm_kernels.py"
MODULE_NAME = "_srm_aot"

_state: dict[str, Any] = {}


# ----------------------------------------------------------------- the key
def _cpu_flags() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("flags", "Features")):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.machine() + " " + platform.processor()


def key(source: Path = SOURCE) -> str:
    """Hash of what an AOT module depends on: kernel source, numpy, Python ABI, CPU."""
    import numpy as np

    h = hashlib.sha256()
    h.update(source.read_bytes())
    for part in (np.__version__, sysconfig.get_config_var("EXT_SUFFIX") or "", sys.version, _cpu_flags()):
        h.update(b"\0" + str(part).encode())
    return h.hexdigest()[:16]


def default_dir() -> Path:
    """Where AOT modules live: the kernels' ``__pycache__`` (beside numba's own cache)."""
    return Path(os.environ.get("SCMR_AOT_DIR") or _HERE / "__pycache__")


def paths(k: str, directory: Path | None = None) -> tuple[Path, Path]:
    """``(module.so, signatures.json)`` for key ``k``."""
    d = directory or default_dir()
    return d / f"{MODULE_NAME}.{k}.so", d / f"{MODULE_NAME}.{k}.json"


# ------------------------------------------------------------------ run time
def _jit(name: str) -> Callable:
    from scmr_mesh.imaging import _srm_kernels

    return getattr(_srm_kernels, name)


def _load(directory: Path | None = None) -> tuple[Any, dict] | tuple[None, str]:
    """The AOT module and its signature table, or ``(None, reason)``."""
    if os.environ.get(ENV, "1").strip() in ("0", "no", "off", "false"):
        return None, f"{ENV}=0"
    try:
        k = key()
    except OSError as exc:
        return None, f"kernel source unreadable ({exc})"
    so, meta = paths(k, directory)
    if not so.is_file() or not meta.is_file():
        return None, f"no AOT module for key {k} in {so.parent} (run `python -m scmr_mesh.imaging._aot`)"
    try:
        table = json.loads(meta.read_text())
        import importlib.machinery
        import importlib.util

        loader = importlib.machinery.ExtensionFileLoader(f"scmr_mesh.imaging.{MODULE_NAME}", str(so))
        spec = importlib.util.spec_from_file_location(f"scmr_mesh.imaging.{MODULE_NAME}", str(so), loader=loader)
        mod = importlib.util.module_from_spec(spec)
        loader.exec_module(mod)
    except Exception as exc:  # a broken or foreign file: the JIT is always right
        return None, f"AOT module {so} unusable ({type(exc).__name__}: {exc})"
    return mod, table


def _module():
    if "module" not in _state:
        mod, info = _load()
        _state["module"], _state["info"] = mod, info
        if mod is None:
            log.debug("pipeline kernels: numba JIT (%s)", info)
    return _state["module"], _state["info"]


def status() -> str:
    """``"aot <key>"`` or ``"jit (<reason>)"``: which kernels this process uses."""
    mod, info = _module()
    return f"aot {info.get('key')}" if mod is not None else f"jit ({info})"


def kernel(name: str) -> Callable:
    """The kernel ``name``: the guarded AOT function, or the numba dispatcher."""
    if name not in KERNELS:
        raise AttributeError(f"{__name__} has no kernel {name!r}; kernels: {KERNELS}")
    mod, info = _module()
    if mod is not None and name in info.get("signatures", {}) and hasattr(mod, name):
        return _guarded(name, getattr(mod, name), info["signatures"][name])
    return _jit(name)


def __getattr__(name: str) -> Callable:  # `from scmr_mesh.imaging._aot import srm_kernel`
    if name in KERNELS:
        fn = kernel(name)
        globals()[name] = fn
        return fn
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _arg_check(spec: dict) -> Callable[[Any], bool]:
    import numpy as np

    kind = spec["kind"]
    if kind == "array":
        dtype, ndim, contiguous = np.dtype(spec["dtype"]), int(spec["ndim"]), spec["layout"] == "C"
        return lambda a: (type(a) is np.ndarray and a.dtype == dtype and a.ndim == ndim
                          and (not contiguous or a.flags.c_contiguous))
    if kind == "float":
        return lambda a: isinstance(a, (float, int, np.floating, np.integer)) and not isinstance(a, (bool, np.bool_))
    if kind == "int":
        return lambda a: isinstance(a, (int, np.integer)) and not isinstance(a, (bool, np.bool_))
    raise ValueError(f"unknown argument kind {kind!r}")


def _guarded(name: str, fn: Callable, sig: list[dict]) -> Callable:
    """``fn`` when the arguments have the built types, else the JIT dispatcher."""
    checks = [_arg_check(s) for s in sig]
    n = len(checks)

    def call(*args):
        # a plain loop: a generator for all() cost about 1 us a call, 0.08 ms a frame (69 calls)
        if len(args) == n:
            for c, a in zip(checks, args):
                if not c(a):
                    break
            else:
                return fn(*args)
        return _jit(name)(*args)

    call.__name__ = name
    call.__doc__ = f"AOT-compiled {name} (falls back to the numba JIT for other argument types)"
    call.aot = fn  # type: ignore[attr-defined]
    return call


# --------------------------------------------------------------------- build
def _arg_spec(t) -> dict:
    """A numba type as a checkable spec (arrays, floats, ints only)."""
    from numba.core import types

    if isinstance(t, types.Array):
        return {"kind": "array", "dtype": str(t.dtype), "ndim": t.ndim, "layout": t.layout}
    if isinstance(t, types.Float):
        return {"kind": "float"}
    if isinstance(t, types.Integer) and not isinstance(t, types.Boolean):
        return {"kind": "int"}
    raise TypeError(f"argument type {t} not supported by the AOT build")


def build(directory: Path | None = None, *, force: bool = False) -> Path:
    """Compile the kernels for this machine; return the module's path.

    Runs the pipeline's warm-up with the JIT to learn each kernel's argument
    types, then ``numba.pycc`` (needs a C compiler).  Does nothing when the
    module for the current key exists (unless ``force``).  Older modules in
    the directory are removed.

    Raises
    ------
    RuntimeError
        When a kernel was called with more than one signature or pycc fails.
    """
    import shutil
    import tempfile
    import warnings

    os.environ[ENV] = "0"  # learn the signatures from the JIT, not from an old module
    _state.clear()
    k = key()
    directory = Path(directory or default_dir())
    so, meta = paths(k, directory)
    if so.is_file() and meta.is_file() and not force:
        return so
    from scmr_mesh.imaging import _srm_kernels
    from scmr_mesh.imaging.pipeline import warm_up

    warm_up()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pycc is pending deprecation in numba
        from numba.pycc import CC

    cc = CC(MODULE_NAME)
    cc.target_cpu = "host"  # the JIT's code quality; the key pins the CPU
    cc.verbose = False
    table: dict[str, list[dict]] = {}
    for name in KERNELS:
        disp = getattr(_srm_kernels, name)
        sigs = list(disp.nopython_signatures)
        if len(sigs) != 1:
            raise RuntimeError(f"kernel {name} has {len(sigs)} compiled signatures after warm_up "
                               f"({sigs}); the AOT build needs exactly one")
        sig = sigs[0]
        table[name] = [_arg_spec(t) for t in sig.args]
        cc.export(name, sig)(disp.py_func)
    directory.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="scmr-aot-") as tmp:
        cc.output_dir = tmp
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cc.compile()
        built = next(Path(tmp).glob(f"{MODULE_NAME}*.so"))
        tmp_so = directory / f".{so.name}.{os.getpid()}"
        shutil.copyfile(built, tmp_so)
        os.replace(tmp_so, so)
    import numba

    meta.write_text(json.dumps({"key": k, "signatures": table, "numba": numba.__version__,
                                "source": str(SOURCE)}, indent=1) + "\n")
    for old in directory.glob(f"{MODULE_NAME}.*"):
        if old not in (so, meta):
            try:
                old.unlink()
            except OSError:
                pass
    return so


def main(argv: list[str] | None = None) -> int:
    """``python -m scmr_mesh.imaging._aot [--force] [--dir DIR]``: build; never fails the caller's make."""
    import argparse
    import time

    p = argparse.ArgumentParser(prog="python -m scmr_mesh.imaging._aot",
                                description="Compile the pipeline kernels ahead of time (numba.pycc).")
    p.add_argument("--force", action="store_true", help="rebuild even when a module for this key exists")
    p.add_argument("--dir", default=None, help="output directory (default: the kernels' __pycache__)")
    args = p.parse_args(argv)
    t0 = time.monotonic()
    try:
        so = build(Path(args.dir) if args.dir else None, force=args.force)
    except Exception as exc:
        print(f"scmr: AOT kernels not built ({type(exc).__name__}: {exc}); the pipeline uses the numba JIT "
              "(start-up ~0.3 s slower)", file=sys.stderr)
        return 1
    print(f"AOT kernels: {so} ({time.monotonic() - t0:.1f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

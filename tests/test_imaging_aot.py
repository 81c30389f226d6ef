"""The ahead-of-time compiled kernels (imaging/_aot.py) against the numba JIT.

The AOT module is built once per session into a temporary directory (a C
compiler is needed, as for ``make``), or copied from the package's ``__pycache__``
when ``make`` built it there after the last change to ``_aot.py`` and the kernels.  Each check runs in a fresh interpreter
so that "numba is never imported" can be observed.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from scmr_mesh.imaging import _aot


def _py(code: str, env: dict, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env={**os.environ, **env},
                          capture_output=True, text=True, timeout=timeout)


def _prebuilt() -> tuple[Path, Path] | None:
    """The module ``make`` built (``python -m scmr_mesh.imaging._aot``, as ``make test`` runs first) for
    the current key (it hashes the kernels), when it is newer than the build code and the kernels (what
    the Makefile rebuilds it for): the build the session would repeat."""
    so, meta = _aot.paths(_aot.key())
    if not (so.is_file() and meta.is_file()):
        return None
    newest = max(Path(_aot.__file__).stat().st_mtime, _aot.SOURCE.stat().st_mtime)
    return (so, meta) if min(so.stat().st_mtime, meta.stat().st_mtime) > newest else None


@pytest.fixture(scope="module")
def aot_dir(tmp_path_factory) -> Path:
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler: the AOT build needs one (the pipeline then uses the numba JIT)")
    d = tmp_path_factory.mktemp("aot")
    built = _prebuilt()
    if built is not None:  # a copy: the checks below never touch the package's own module
        for f in built:
            shutil.copy2(f, d / f.name)
        return d
    r = subprocess.run([sys.executable, "-m", "scmr_mesh.imaging._aot", "--dir", str(d)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return d


def test_build_writes_module_and_signatures_for_the_current_key(aot_dir):
    so, meta = _aot.paths(_aot.key(), aot_dir)
    assert so.is_file() and meta.is_file()
    table = json.loads(meta.read_text())
    assert set(table["signatures"]) == set(_aot.KERNELS)
    assert table["signatures"]["srm_kernel"][0] == {"kind": "array", "dtype": "uint8", "ndim": 3, "layout": "C"}


def test_pipeline_runs_without_numba_and_matches_the_jit(aot_dir):
    code = """
        import sys, numpy as np
        from scmr_mesh.imaging import _aot, segment_drivable
        from scmr_mesh.imaging.synthetic import make_scene, SCENE_KINDS
        assert _aot.status().startswith("aot"), _aot.status()
        masks = {}
        for i, kind in enumerate(SCENE_KINDS):
            rgb, _ = make_scene(kind, seed=i)
            for mode in ("best", "thesis"):
                masks[(kind, mode)] = segment_drivable(rgb, mode=mode).mask
        assert "numba" not in sys.modules, "the AOT path imported numba"
        # the same frames through the JIT dispatchers
        from scmr_mesh.imaging import _srm_kernels as jit
        for name in _aot.KERNELS:
            _aot.__dict__[name] = getattr(jit, name)
        for (kind, mode), m in masks.items():
            rgb, _ = make_scene(kind, seed=list(SCENE_KINDS).index(kind))
            assert (segment_drivable(rgb, mode=mode).mask == m).all(), (kind, mode)
        rng = np.random.default_rng(5)
        for shape, q, ms in (((7, 9, 3), 32.0, 0), ((40, 33, 3), 8.0, 5), ((225, 300, 3), 512.0, 10)):
            img = rng.integers(0, 256, shape, dtype=np.uint8)
            t = jit.b2_table(shape[0] * shape[1], q)
            np.testing.assert_array_equal(_aot.kernel("b2_table")(shape[0] * shape[1], q), t)
            a = _aot.kernel("srm_kernel")(img, q, ms, t)
            b = jit.srm_kernel(img, q, ms, t)
            assert all((x == y).all() and x.dtype == y.dtype for x, y in zip(a, b)), shape
        print("ok", len(masks))
    """
    r = _py(code, {"SCMR_AOT_DIR": str(aot_dir)})
    assert r.returncode == 0 and "ok 10" in r.stdout, r.stdout + r.stderr


def test_arguments_of_other_types_go_to_the_jit_instead_of_crashing(aot_dir):
    # pycc's own wrapper reads a strided or int32 array as if it were C-contiguous
    # uint8 (a segfault was seen); the guard must send such calls to the JIT
    code = """
        import sys, numpy as np
        from scmr_mesh.imaging import _aot
        from scmr_mesh.imaging import _srm_kernels as jit
        f = _aot.kernel("srm_kernel")
        assert hasattr(f, "aot")
        img = np.random.default_rng(1).integers(0, 256, (20, 30, 3), dtype=np.uint8)
        t = jit.b2_table(600, 32.0)
        for args in ((img[:, ::2], 32.0, 1, t), (img.astype(np.int32), 32.0, 1, t), (img[0], 32.0, 1, t)):
            try:
                got = f(*args)
            except Exception as exc:  # the JIT's own type error is fine
                got = type(exc).__name__
            try:
                want = jit.srm_kernel(*args)
            except Exception as exc:
                want = type(exc).__name__
            if isinstance(want, str):
                assert got == want, (got, want)
            else:
                assert all((x == y).all() for x, y in zip(got, want))
        print("ok")
    """
    r = _py(code, {"SCMR_AOT_DIR": str(aot_dir)})
    assert r.returncode == 0 and "ok" in r.stdout, r.stdout + r.stderr


def test_a_module_built_from_other_kernels_is_not_loaded(aot_dir, tmp_path):
    # a copy of the AOT files under another key (as after the kernels changed)
    so, meta = _aot.paths(_aot.key(), aot_dir)
    src = tmp_path / "_srm_kernels.py"
    src.write_text(_aot.SOURCE.read_text() + "\n# changed\n")
    other = _aot.key(src)
    assert other != _aot.key()
    stale = tmp_path / "stale"
    stale.mkdir()
    so2, meta2 = _aot.paths(other, stale)
    shutil.copy(so, so2)
    shutil.copy(meta, meta2)
    r = _py("from scmr_mesh.imaging import _aot; print(_aot.status())", {"SCMR_AOT_DIR": str(stale)})
    assert r.returncode == 0 and r.stdout.startswith("jit (no AOT module"), r.stdout + r.stderr


def test_switched_off_by_environment(aot_dir):
    r = _py("from scmr_mesh.imaging import _aot; print(_aot.status())",
            {"SCMR_AOT_DIR": str(aot_dir), "SCMR_AOT": "0"})
    assert r.stdout.strip() == "jit (SCMR_AOT=0)", r.stdout + r.stderr

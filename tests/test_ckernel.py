"""mono_map/ckernel.py: the C kernels' sources, the libraries pip install builds from them (setup.py), the
run-time cache for a missing or stale library, and the header that mirrors materials.py."""

import ctypes
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mono_map import ckernel

REPO = Path(__file__).resolve().parents[1]


def test_setup_builds_the_libraries_the_package_loads(tmp_path, monkeypatch):
    """setup.py's build_ext writes mono_map/_lib/<name>_<digest>.so for every kernel; ckernel takes exactly
    those (no run-time compile), and they are byte for byte what the run-time fallback compiles."""
    if shutil.which(os.environ.get("CC", "cc")) is None:
        pytest.skip("no C compiler")
    monkeypatch.setenv("MONO_MAP_CACHE", str(tmp_path / "cache"))
    subprocess.run([sys.executable, "setup.py", "-q", "build_ext", "--build-lib", str(tmp_path / "lib"),
                    "--build-temp", str(tmp_path / "tmp")], cwd=REPO, check=True, capture_output=True)
    built = tmp_path / "lib" / "mono_map" / "_lib"
    assert sorted(p.name for p in built.iterdir()) == sorted(ckernel.built_name(n) for n in ckernel.LIBRARIES)
    for name in ckernel.LIBRARIES:
        assert ckernel.library_path(name, built_dir=built) == built / ckernel.built_name(name)
    assert not (tmp_path / "cache").exists()
    assert ckernel.load("raycast", {}, built_dir=built).mm_ray_cells is not None
    fresh = ckernel.library_path("points", built_dir=tmp_path / "none")        # the run-time path
    assert fresh.parent == tmp_path / "cache"
    assert fresh.read_bytes() == (built / ckernel.built_name("points")).read_bytes()


def _twice_source(tmp_path):
    """A one-function kernel with a local header, in tmp_path/src."""
    src = tmp_path / "src"
    src.mkdir()
    (src / "twice.h").write_text("#define FACTOR 2.0f\n")
    (src / "mm_test.c").write_text('#include "twice.h"\nfloat mm_twice(float x) { return FACTOR * x; }\n')
    return src


def test_ckernel_builds_once_into_its_cache(tmp_path, monkeypatch):
    """A kernel without an installed library compiles once into the cache; an edited header makes a new one."""
    if shutil.which("cc") is None:
        pytest.skip("no C compiler")
    monkeypatch.setenv("MONO_MAP_CACHE", str(tmp_path / "cache"))
    src, sig = _twice_source(tmp_path), {"mm_twice": ([ctypes.c_float], ctypes.c_float)}
    lib = ckernel.load("mm_test", sig, src, tmp_path / "lib")
    assert lib is not None and lib.mm_twice(1.25) == 2.5
    built = sorted((tmp_path / "cache").glob("mm_test_*.so"))
    assert len(built) == 1 and ckernel.digest("mm_test", src) in built[0].name
    mtime = built[0].stat().st_mtime_ns
    assert ckernel.load("mm_test", sig, src, tmp_path / "lib") is not None
    assert built[0].stat().st_mtime_ns == mtime and sorted((tmp_path / "cache").glob("mm_test_*")) == built
    (src / "twice.h").write_text("#define FACTOR 3.0f\n")          # the header is part of the digest
    assert ckernel.load("mm_test", sig, src, tmp_path / "lib").mm_twice(1.25) == 3.75
    assert len(list((tmp_path / "cache").glob("mm_test_*.so"))) == 2


def test_ckernel_takes_the_installed_library_only_while_current(tmp_path, monkeypatch):
    """The library built at install (<name>_<digest>.so) is loaded as it is; once the source changes its
    digest no longer matches and the source is compiled into the cache instead."""
    if shutil.which("cc") is None:
        pytest.skip("no C compiler")
    monkeypatch.setenv("MONO_MAP_CACHE", str(tmp_path / "cache"))
    src, sig = _twice_source(tmp_path), {"mm_twice": ([ctypes.c_float], ctypes.c_float)}
    installed = tmp_path / "lib" / ckernel.built_name("mm_test", src)
    ckernel.compile_library(src / "mm_test.c", installed)
    assert ckernel.library_path("mm_test", src, tmp_path / "lib") == installed
    assert ckernel.load("mm_test", sig, src, tmp_path / "lib").mm_twice(2.0) == 4.0
    assert not (tmp_path / "cache").exists()                      # nothing compiled at run time
    (src / "mm_test.c").write_text('#include "twice.h"\nfloat mm_twice(float x) { return FACTOR * x + 1.0f; }\n')
    stale = ckernel.library_path("mm_test", src, tmp_path / "lib")
    assert stale != installed and stale.parent == tmp_path / "cache"
    assert ckernel.load("mm_test", sig, src, tmp_path / "lib").mm_twice(2.0) == 5.0


def test_synth_header_matches_materials():
    """csrc/synth_materials.h holds materials.py's ids (MAT_<NAME>) and LiDAR reflectances, value for value."""
    import re

    from mono_map.data.synth import materials as M

    text = (ckernel.SOURCE_DIR / "synth_materials.h").read_text()
    defines = {name: int(v) for name, v in re.findall(r"#define MAT_(\w+) (\d+)", text)}
    assert defines == {k: v for k, v in vars(M).items() if k.isupper() and isinstance(v, int)}
    body = re.search(r"lidar_refl\(int m\) \{ switch \(m\) \{ (.*) default: return ([0-9.]+); \} \}", text)
    cases = {int(m): float(r) for m, r in re.findall(r"case (\d+): return ([0-9.e-]+);", body.group(1))}
    assert cases == {int(m): float(r) for m, r in M.LIDAR_REFL.items()}
    assert float(body.group(2)) == 0.3

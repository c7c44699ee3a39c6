"""Build the C kernels at install: ``mono_map/csrc/<name>.c`` -> ``mono_map/_lib/<name>_<digest>.so``.

The libraries are plain shared libraries loaded with ctypes (no Python API), compiled with
``mono_map.ckernel``'s flags (``-O3``, IEEE: ``-ffp-contract=off -fno-fast-math``, ``-Wall``) so an
installed library is the one the run-time fallback would build. A failed build only warns: the
package then compiles the kernels on first use, or runs its numpy paths without a compiler.
Everything else (metadata, dependencies, package data) is in pyproject.toml.
"""

import importlib.util
import os
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext
from setuptools.errors import CompileError

HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("mono_map_ckernel", HERE / "mono_map" / "ckernel.py")
ckernel = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(ckernel)   # standard library only: no need for the package's dependencies


class BuildKernels(build_ext):
    """build_ext for the ctypes kernels: the digest-named file, compiled with ckernel's own flags."""

    def get_ext_filename(self, fullname):
        *package, name = fullname.split(".")
        return os.path.join(*package, ckernel.built_name(name, HERE / "mono_map" / "csrc"))

    def copy_extensions_to_source(self):
        """Editable installs (pip install -e .) copy the libraries into the source tree's mono_map/_lib/."""
        (HERE / "mono_map" / "_lib").mkdir(exist_ok=True)
        super().copy_extensions_to_source()

    def build_extension(self, ext):
        out = Path(self.get_ext_fullpath(ext.name))
        try:
            ckernel.compile_library(HERE / ext.sources[0], out, quiet=False)
        except (OSError, ckernel.subprocess.SubprocessError) as exc:
            raise CompileError(f"{ext.sources[0]}: {exc}") from exc


setup(
    ext_modules=[
        Extension(f"mono_map._lib.{name}", sources=[f"mono_map/csrc/{name}.c"],
                  depends=[str(p.relative_to(HERE)) for p in ckernel.source_files(name, HERE / "mono_map" / "csrc")],
                  optional=True)
        for name in ckernel.LIBRARIES
    ],
    cmdclass={"build_ext": BuildKernels},
)

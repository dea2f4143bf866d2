"""Build of gridcal's compiled extension: kernels/ (C99) plus the thin binding.

Precise floating point throughout: no fast-math, no contraction into fused
multiply-adds (the watertight intersector depends on unfused products).
"""
import subprocess

import numpy
from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

KERNEL_SOURCES = ["grid.c", "build.c", "overlap.c", "traverse.c", "brute.c", "stats.c", "bigmem.c"]
CFLAGS = ["-std=c99", "-O2", "-pthread", "-ffp-contract=off", "-fno-fast-math"]


class BuildExt(build_ext):
    """Record the compiler and flags in the module, for the host fingerprint."""

    def build_extensions(self):
        cc = self.compiler.compiler_so[0] if hasattr(self.compiler, "compiler_so") else "cc"
        try:
            version = subprocess.run([cc, "--version"], capture_output=True, text=True,
                                     timeout=30).stdout.splitlines()[0]
        except (OSError, IndexError, subprocess.SubprocessError):
            version = cc
        described = f"{version}; {' '.join(CFLAGS)}".replace('"', "'").replace("\\", "/")
        for ext in self.extensions:
            ext.define_macros.append(("GRIDCAL_CFLAGS", f'"{described}"'))
        super().build_extensions()


setup(
    ext_modules=[
        Extension(
            "calibrate._kernels",
            sources=["calibrate/_kernels.c"] + [f"kernels/{s}" for s in KERNEL_SOURCES],
            include_dirs=["kernels", numpy.get_include()],
            extra_compile_args=CFLAGS,
            extra_link_args=["-pthread"],
            depends=[f"kernels/{h}" for h in
                     ["gridcal.h", "gc_internal.h", "box.h", "triangle.h", "traverse_impl.h"]],
        )
    ],
    cmdclass={"build_ext": BuildExt},
)

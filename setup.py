"""Build of rcotorch's native engine, the C extension ``rcotorch.engine._engine`` (the rest is in pyproject.toml).

``pip install .`` and ``pip install -e .`` compile ``rcotorch/engine/csrc/engine.c`` with the C compiler Python was
built with (OpenMP when the compiler has it). The extension is optional: without a working compiler the
package still installs, says so once here, and runs everything on PyTorch (``rcotorch.engine.kernels`` warns once at
import). It needs no torch at build time: the kernels take tensors as addresses and sizes.
"""

import sys

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

# Plain IEEE double arithmetic: no contraction into FMA, no reassociation, so a member's result does not
# depend on the instruction set, the lane width or the batch it runs in.
# Loops over lanes are marked for vectorization (OpenMP simd, no OpenMP runtime needed); -fno-trapping-math
# and -fno-math-errno let selects and square roots vectorize and change no value. Functions start on a cache
# line: one member's step runs in a few functions, so aligning them keeps its time from depending on where
# a build happens to place them. -fno-wrapv undoes Python's -fwrapv (the engine's integers never overflow; its
# hashes are unsigned), so the compiler may simplify the index arithmetic.
FLAGS = ["-O3", "-ftree-vectorize", "-fvect-cost-model=dynamic", "-ffp-contract=off", "-fno-math-errno",
         "-fno-trapping-math", "-fno-tree-loop-distribute-patterns", "-fopenmp-simd", "-std=gnu11",
         "-falign-functions=64", "-fno-wrapv"]
OPENMP = ["-fopenmp"]


class BuildEngine(build_ext):
    """Compile with OpenMP if the compiler has it, else without (one thread); never fail the install."""

    def build_extension(self, ext):
        for extra in (OPENMP, []):
            ext.extra_compile_args = FLAGS + extra
            ext.extra_link_args = list(extra)
            try:
                super().build_extension(ext)
                return
            except Exception as e:  # a compiler without OpenMP, or none at all
                err = e
        sys.stderr.write(f"rcotorch: the native engine was not built ({err}); rcotorch will run on PyTorch "
                         "only. Install a C compiler and reinstall to build it.\n")


setup(
    ext_modules=[Extension("rcotorch.engine._engine", sources=["rcotorch/engine/csrc/engine.c"],
                           depends=["rcotorch/engine/csrc/engine.h", "rcotorch/engine/csrc/lanes.h",
                                    "rcotorch/engine/csrc/widths.h", "rcotorch/engine/csrc/replay.h"], optional=True)],
    cmdclass={"build_ext": BuildEngine},
)

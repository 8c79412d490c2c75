"""The project's two compiled parts (see their sources); everything else is in pyproject.toml.

- robot_sim.arm._pinocchio_inplace, compiled against the headers and libraries of the
  pin wheel in the build environment (pinned to the runtime's version in
  pyproject.toml) and the Eigen headers of cmeel-eigen.  Without it robot_sim falls
  back to Pinocchio's bindings, which allocate two small vectors per control step.
- kernel_plumbing._json_numbers, a float64 as orjson writes it, for kernels that write
  messages' bytes (C++17's std::to_chars; no dependency).  Without it the messages are
  written by orjson, the same bytes.

Both are optional: without a C++ compiler the install goes on without them.
"""

import shutil
import sys
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext


def cmeel_prefix() -> Path:
    """The cmeel prefix holding Pinocchio's and Eigen's headers (pin, cmeel-eigen)."""
    for entry in sys.path:
        prefix = Path(entry) / "cmeel.prefix"
        if (prefix / "include" / "pinocchio").is_dir() and (prefix / "include" / "eigen3").is_dir():
            return prefix
    raise SystemExit("setup.py: no cmeel.prefix with include/pinocchio and include/eigen3 on sys.path; "
                     "the build needs the pin and cmeel-eigen wheels (build-system.requires in pyproject.toml)")


def pinocchio_inplace() -> Extension:
    import numpy

    prefix = cmeel_prefix()
    lib = prefix / "lib"
    return Extension(
        "robot_sim.arm._pinocchio_inplace",
        sources=["robot_sim/arm/native/pinocchio_inplace.cpp"],
        include_dirs=[str(prefix / "include"), str(prefix / "include" / "eigen3"), numpy.get_include()],
        # the compile definitions of the pinocchio::pinocchio_default CMake target
        # (lib/cmake/pinocchio/pinocchioTargets.cmake): they fix the joint variant's size
        define_macros=[("BOOST_MPL_LIMIT_LIST_SIZE", "30"), ("BOOST_MPL_LIMIT_VECTOR_SIZE", "30"),
                       ("BOOST_MPL_CFG_NO_PREPROCESSED_HEADERS", None), ("BOOST_FUSION_INVOKE_MAX_ARITY", "12"),
                       ("PINOCCHIO_ENABLE_TEMPLATE_INSTANTIATION", None), ("PINOCCHIO_WITH_COLLISION", None)],
        library_dirs=[str(lib)],
        libraries=["pinocchio_default", "eigenpy", f"boost_python{sys.version_info.major}{sys.version_info.minor}"],
        # installed: site-packages/robot_sim/arm -> site-packages/cmeel.prefix/lib; an
        # editable install finds them because `import pinocchio` loaded them first
        runtime_library_dirs=["$ORIGIN/../../cmeel.prefix/lib"],
        extra_compile_args=["-std=c++17", "-O2", "-g0", "-Wno-deprecated-declarations"],
        language="c++",
        optional=True,
    )


def json_numbers() -> Extension:
    return Extension("kernel_plumbing._json_numbers", sources=["kernel_plumbing/native/json_numbers.cpp"],
                     extra_compile_args=["-std=c++17", "-O2", "-g0"], language="c++", optional=True)


class BuildExt(build_ext):
    """A wheel's build takes the extension an editable install compiled in place (``make
    venv``), when it is newer than its sources, instead of compiling it again (12 s of one
    core: docker/setup-podman.sh builds the image's wheel from the checkout).  Both builds
    compile the same source against the same pinned headers (build-system.requires)."""

    def build_extension(self, ext):
        if not self.inplace:
            built = Path(self.get_ext_filename(ext.name))  # where an in-place build puts it
            sources = [Path(source) for source in ext.sources] + [Path(__file__)]
            if built.is_file() and all(built.stat().st_mtime > source.stat().st_mtime for source in sources):
                target = Path(self.get_ext_fullpath(ext.name))
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(built, target)
                return
        super().build_extension(ext)


setup(ext_modules=[pinocchio_inplace(), json_numbers()], cmdclass={"build_ext": BuildExt})

"""The optional oneDNN extension (csrc/onednn_conv.cc -> cdrl/_onednn_conv*.so): the
convolution passes of `--conv onednn` as XLA FFI handlers. Everything else is in pyproject.toml.

The build needs a C++ compiler, jaxlib's XLA FFI headers and oneDNN's headers and library (the
build requirements in pyproject.toml). Where any is missing, or the platform is not Linux on
x86-64, the package installs without the extension and `--conv onednn` runs XLA's formulation
with one warning (`cdrl.models.onednn_conv`).
"""
import importlib.metadata
import importlib.util
import os
import platform
import sys

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext


def _located(dist: str, name: str) -> str | None:
    """The absolute path of the file called `name` that the installed distribution `dist` holds."""
    try:
        files = importlib.metadata.distribution(dist).files or []
    except importlib.metadata.PackageNotFoundError:
        return None
    return next((str(f.locate()) for f in files if f.name == name), None)


def _onednn_extension() -> list[Extension]:
    if sys.platform != "linux" or platform.machine() != "x86_64":
        print(f"cdrl: no oneDNN extension on {sys.platform} {platform.machine()}", file=sys.stderr)
        return []
    jaxlib = importlib.util.find_spec("jaxlib")
    header = _located("onednn-devel-cpu-gomp", "dnnl.hpp")
    library = _located("onednn-cpu-gomp", "libdnnl.so.3")
    if jaxlib is None or header is None or library is None:
        print("cdrl: no oneDNN extension (jaxlib or oneDNN's wheels are missing from the build environment)",
              file=sys.stderr)
        return []
    ffi_include = os.path.join(os.path.dirname(jaxlib.origin), "include")
    # .../include/dnnl.hpp forwards to .../include/oneapi/dnnl/dnnl.hpp
    dnnl_include = os.path.dirname(header)
    return [Extension(
        "cdrl._onednn_conv", sources=["csrc/onednn_conv.cc"], language="c++", optional=True,
        include_dirs=[ffi_include, dnnl_include],
        # libdnnl.so.3 by its soname: at run time cdrl loads the environment's copy first
        extra_link_args=[f"-L{os.path.dirname(library)}", "-l:libdnnl.so.3", "-fopenmp"],
        extra_compile_args=["-std=c++17", "-O2", "-fopenmp", "-Wno-attributes",
                            "-Wno-return-type"],
    )]


class OptionalBuildExt(build_ext):
    """A failed compile leaves the package without the extension, with a warning."""

    def build_extension(self, ext):
        try:
            super().build_extension(ext)
        except Exception as e:  # noqa: BLE001 - any failure means: no extension
            print(f"cdrl: the oneDNN extension did not build ({e}); --conv onednn will run XLA's convolutions",
                  file=sys.stderr)


setup(ext_modules=_onednn_extension(), cmdclass={"build_ext": OptionalBuildExt})

"""The compiled kernels (recon/_kernels.c): everything else about the package is in pyproject.toml.

setuptools reads extension modules from here; `pip install .` (and the editable install that
`make setup` does) compiles the kernels with the machine's C compiler. The flags are part of the
kernels' contract with their numpy references (recon/kernels.py): no fused multiply-add, so
each product rounds as numpy's does.
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "recon._kernels",
            sources=["recon/_kernels.c"],
            extra_compile_args=["-O3", "-std=c11", "-ffp-contract=off", "-fno-fast-math"],
        )
    ]
)

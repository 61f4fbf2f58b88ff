"""The compiled part of mavest: the extension ``mavest.estimator._online`` (Cython).

Optional: where it cannot be built (no C compiler), mavest installs without it and
runs the same online step through numba's entry point instead (a few µs a sample
slower, the same results). Everything else is in pyproject.toml.
"""

import hashlib
from pathlib import Path

import numpy
from setuptools import Extension, setup

SOURCE = "mavest/estimator/_online.pyx"
# The build says which source it came from, so that mavest can refuse a stale one.
DIGEST = hashlib.sha256((Path(__file__).parent / SOURCE).read_bytes()).hexdigest()

setup(
    ext_modules=[
        Extension(
            "mavest.estimator._online",
            [SOURCE],
            include_dirs=[numpy.get_include()],
            define_macros=[
                ("NPY_NO_DEPRECATED_API", "NPY_1_7_API_VERSION"),
                ("MAVEST_ONLINE_SOURCE_DIGEST", f'"{DIGEST}"'),
            ],
            optional=True,
        )
    ]
)

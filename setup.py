"""Package layout for setuptools; everything else is in pyproject.toml.

The built-in robot descriptions stay in the top-level ``robots/`` folder (the source of truth, next to
the scripts that generate them) and are shipped as the package data ``torchcal/robots/`` of a wheel,
where :func:`torchcal.robot.load.builtin_robots` finds them with ``importlib.resources``.
"""

from setuptools import find_packages, setup

setup(
    # the top-level experiments/ (the code of scripts/: reproductions, benchmarks, studies) runs from a checkout
    # and stays out of the wheel a user installs
    packages=[
        *find_packages(include=["torchcal", "torchcal.*"]),
        "torchcal.robots",
    ],
    package_dir={"torchcal.robots": "robots"},
    # package data lives here, not in pyproject.toml: a [tool.setuptools.package-data] table there replaces
    # this argument as a whole, and the wheel then ships without its robots
    package_data={"torchcal": ["py.typed"], "torchcal.robots": ["*.urdf", "*.yaml", "*.yml", "README.md"]},
    include_package_data=False,
)

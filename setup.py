"""The compiled part of magnet (its filters' per-sample loops, magnet/_kernels.c; docs/cost.md): everything else is
declared in pyproject.toml. Built by pip from source on install with the machine's C compiler; nothing is
downloaded."""

from setuptools import Extension, setup

setup(ext_modules=[Extension("magnet._kernels", ["magnet/_kernels.c"])])

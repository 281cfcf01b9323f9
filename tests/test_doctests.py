"""Every docstring example in the package runs and shows what it says."""

import doctest
import importlib
import pkgutil

import pytest

PACKAGES = ("gara_jax", "envs", "experiments")
# Run elsewhere: envs.point_maze's examples compile brax's step, which test_point_maze.py has
# compiled (optimised) already, and brax runs faster optimised.
ELSEWHERE = {"envs.point_maze": "tests/test_point_maze.py::test_docstring_examples"}


def _modules():
    """The package modules that have docstring examples."""
    names = []
    for package in PACKAGES:
        pkg = importlib.import_module(package)
        names.append(package)
        names += [info.name for info in pkgutil.walk_packages(pkg.__path__, prefix=f"{package}.")]
    finder = doctest.DocTestFinder()
    has_examples = lambda name: any(t.examples for t in finder.find(importlib.import_module(name)))
    return sorted(name for name in names if name not in ELSEWHERE and has_examples(name))


@pytest.mark.parametrize("name", _modules())
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"

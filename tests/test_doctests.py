"""The ``Examples:`` in the public API's docstrings run (and agree with their printed output).

The same examples run with ``pytest --doctest-modules src/motionflows/distributions.py``
(``doctest_optionflags`` in pyproject.toml); this test keeps them in the default suite.
"""

from __future__ import annotations

import doctest
import importlib

import pytest

MODULES = [
    "motionflows.deprecation",
    "motionflows.distributions",
    "motionflows.pretrained",
    "motionflows.run",
]


FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=FLAGS, report=True)
    assert result.attempted > 0, f"{name} has no docstring examples"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples of {name} failed"

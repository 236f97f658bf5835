"""Experiment modules: ``python -m experiments.<name> --preset quick --data synthetic``.

Each module follows the protocol in ``docs/ARCHITECTURE.md`` and is run by
``motionflows.training`` (``motionflows.training.experiment_main(module)``). The package is
installed with motionflows, and each module is registered in the ``motionflows.experiments``
entry-point group of ``pyproject.toml``: the library finds experiments only there.
"""

"""Experiment modules: ``python -m experiments.<name> --preset quick --data synthetic``.

Each module follows the protocol in ``docs/ARCHITECTURE.md`` and is run by
``motionflows.training`` (``motionflows.training.experiment_main(module)``).
"""

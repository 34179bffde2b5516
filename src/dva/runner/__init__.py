"""The runner: the one training loop (:mod:`dva.runner.training`), the one evaluation
(:mod:`dva.runner.evaluation`), Weights & Biases logging (:mod:`dva.runner.tracking`), one run's
environments split over several devices (:mod:`dva.runner.sharding`) and the process-wide set-up
runs need (:mod:`dva.runner.runtime`, ``dva.configure()``).

Importing this package loads nothing heavy: ``import dva`` takes ``configure`` from it.
"""

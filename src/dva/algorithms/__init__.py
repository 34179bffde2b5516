"""Learning algorithms. D.Va, SHAC and DPG-on-state are one trainer: :mod:`dva.algorithms.shac`."""

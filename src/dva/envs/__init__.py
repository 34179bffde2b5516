"""The environment side: the task registry (:mod:`dva.envs.registry`), the rendered observations
(:mod:`dva.envs.observations`) and their renderers (:mod:`dva.envs.rendering`, Warp's pixels;
:mod:`dva.envs.soft_rendering`, the differentiable one), every task as a Gymnasium environment
(:mod:`dva.envs.gymnasium`) and policy videos (:mod:`dva.envs.visualize`). The tasks' physics
and rewards are :mod:`dva.tasks`.

Importing this package loads nothing heavy: ``import dva`` registers the Gymnasium ids through it.
"""

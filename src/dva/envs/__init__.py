"""The environment side: the one factory from a task name to an environment
(:mod:`dva.envs.factory`), the environment and renderer protocols and the rendered observations
(:mod:`dva.envs.observations`), the renderers (:mod:`dva.envs.rendering`, Warp's pixels;
:mod:`dva.envs.soft_rendering`, the differentiable one), dm_control's tasks (:mod:`dva.envs.dmc`),
every task as a Gymnasium environment (:mod:`dva.envs.gymnasium`) and policy videos
(:mod:`dva.envs.visualize`). The tasks' physics and rewards are :mod:`dva.tasks`.

Importing this package loads nothing heavy: ``import dva`` registers the Gymnasium ids through it.
"""

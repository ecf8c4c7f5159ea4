"""The 2-D figures of every stage (matplotlib, no screen): range images and circle convergence,
score clouds, the pose network and residuals, elevation and the exploration map.

May import: ``core``, ``io``, ``access``, ``params``, ``params.men``, ``outputs.figures``.
"""

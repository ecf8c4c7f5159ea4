"""Where to scan next (Men 2012 ch. 3.3, 3.7-3.8, 6; men_spec 3, 7): occlusion boundaries, the
exploration grid and its frontier, visibility, and the next-vantage planners.

May import: ``core.geometry``, ``core.features``, ``core.exploration``, ``params.men``.
"""

"""Pairwise registration (thesis ch. 5; spec 6-7; men spec 4-5): sub-maps, candidate pairs,
Olson's score and its bounds, branch and bound, pair checks, refinement, colour and Fourier.

May import: ``core.geometry``, ``core.cloud``, ``core.features``, ``core.registration``,
``params``, ``params.men``; nothing from mapping or exploration.
"""

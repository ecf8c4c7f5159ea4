"""Per-scan features (thesis ch. 4; spec 1-5, 9): the levelled range image, scan-line segments,
circle models, cylinder segments, wall lines and the lowest-hit elevation grid.

May import: ``core.geometry``, ``core.cloud``, ``core.features``, ``params``; nothing from
registration, mapping or exploration.
"""

"""The global map (thesis ch. 3, 6-7; spec 8-10): chaining, the Lu-Milios optimal map, residuals
and the link test, link selection, and the integrated map's trees and point cloud.

May import: ``core.geometry``, ``core.cloud``, ``core.features``, ``core.mapping``, ``params``.
"""

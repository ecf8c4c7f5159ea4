"""The method as plain functions on numpy arrays and pandas tables: features, registration,
mapping and exploration, one folder per part of the thesis, no Dagster.

May import: ``forestmap_assets.core``, ``forestmap_assets.params`` and
``forestmap_assets.params.men``, and numpy-level libraries (numpy, scipy, pandas, numba, open3d).
"""

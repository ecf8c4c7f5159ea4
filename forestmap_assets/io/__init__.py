"""Reading and writing what lies on disk: ``campaign.yaml``, scan files of every format (to
organised range images), scan writers, and the Parquet asset store on any fsspec URL.

May import: ``core`` (the range image), ``params``, ``io``; no Dagster except the store's IO
manager.
"""
